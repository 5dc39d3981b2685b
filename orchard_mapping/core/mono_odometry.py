"""Front end of single-side reconstruction from colour only (paper: RGB data, eta = 0, free scale s_c).

`RGBFrontEnd` is `RGBDFrontEnd` (core/odometry.py) without depth: the same KLT tracks with
constant-velocity prediction, RANSAC PnP against landmarks, and keyframes; what differs is where the
landmarks come from and what the unit of length is.

- Initialisation: corners of the first frame are tracked until their median displacement reaches
  `init_parallax_px`; then the essential matrix (RANSAC) and `cv2.recoverPose` give the relative pose
  and the inliers are triangulated. The attempt is accepted once the median triangulation angle reaches
  `init_min_angle_deg` (a rotation-free parallax measure; else it waits for more motion). A two-view
  estimate from a sideways walk confuses rotation with translation direction by degrees (measured:
  0.6 deg of yaw, 3.5 deg of heading at a 2.8 deg median angle), which the map inherits as scale drift,
  so it is refined by a bundle adjustment over up to `init_refine_frames` frames between the two views.
  The two frames become keyframes 0 and 1; the frames between get their pose by PnP.
- Unit: the distance between keyframes 0 and 1 is 1. The map is up to this scale; the RGB-only bundle
  adjustment (core/bundle_adjustment.py, mode "rgb") keeps it free.
- New landmarks: corners detected at a keyframe become pending tracks, KLT-tracked every frame
  (predicted with the constant-velocity pose at the live landmarks' median depth) and recorded at each
  keyframe. A pending track whose rays from its first keyframe and the current one differ by at least
  `min_angle_deg` is triangulated (linear DLT) and kept if it lies in front of, and reprojects within
  `max_reprojection_px` at, every keyframe that saw it; it joins the map with all those observations.
  Live landmarks are re-triangulated from all their keyframe observations at each keyframe (the
  counterpart of the RGB-D depth averaging: on four seeds the front end's scale fitted on either half
  of the path differed by 0.3-4.1 % with it, 3.0-5.1 % without).
- Keyframes: translation relative to the live landmarks' median depth (`keyframe_baseline_ratio`;
  metres mean nothing here), rotation and the live-track count as in RGB-D.
- Observations carry depth 0; keyframe ORB features have no depth.
- Losses: keyframes carry upright ORB descriptors of the landmarks they observe (computed at the tracked
  corners). A lost frame's corners are matched against the landmarks of the last `reloc_keyframes`
  keyframes, guided by the pose extrapolated with the last motion and unguided; each hypothesis's PnP
  pose is grown to every recent landmark it predicts near a matching corner plus the last good frame's
  tracks (KLT started at their predicted pixels), and the largest consensus wins. The frame is thus
  placed against the map, which keeps its scale across the gap; `reentry_ba_keyframes` keyframes later a
  bundle adjustment of the keyframes around the gap (scale held by those before it) refines the re-entry.
  Landmarks are matched with the descriptor of every recent keyframe that saw them (a landmark looks
  different along the row), one pair per landmark and corner. Lost frames that could not be relocalised
  themselves are placed after the re-entry bundle adjustment by tracking back from the current frame (KLT
  frame to frame, topped up from the recent landmarks' descriptors as the tracks thin out). Seeds 11-22
  of the blank-frame test: every frame after the gap placed, ATE 0.04-0.62 % of the path (seed 13:
  frames 53-58 relocalised only by tracking back; before, lost for good).
  A colour frame alone cannot seed a map, so the RGB-D restart does not apply: a loss that cannot be
  relocalised stays lost, and `events` says so, as it does for an initialisation that never succeeds.
  Measured, 8 blank frames in a 2-tree level sweep (test_mono_odometry.py, 640x480, 15 Hz): front-end
  ATE of all placed frames 0.07-0.12 % of the path on seeds 11-13 (the KLT-only bridge it replaces:
  1.37 % on one processor, lost for good on others; at 320x240 the new recovery still failed on 2 of 7 seeds).

Measured (test/unit/core/test_mono_odometry.py, 2-tree row, 15 Hz, 640x480, 99 frames over 3.5 m, seeds
11-13): after RGB-only BA the keyframe ATE is 0.03-0.08 % of the path after a similarity fit, the scale
fitted on either half of the path agrees within 0.02-1.0 %, and the scaled landmarks lie a median 7-8 mm
from the true surfaces.

The relocalisation after a loss and the re-entry bundle adjustment are in core.mono_relocalisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from orchard_mapping.core.bundle_adjustment import ReconstructionError, bundle_adjust
from orchard_mapping.core.keyframe_features import no_keyframe_features
from orchard_mapping.core.mono_relocalisation import MonoRelocalisation
from orchard_mapping.core.odometry import FrontEndParams, RGBDFrontEnd, pose_rotation_deg
from orchard_mapping.core.sidemap import FrontEndResult, Observations
from orchard_mapping.core.types import CameraIntrinsics, RGBDFrame

__all__ = ["MonoParams", "RGBFrontEnd", "triangulate"]

ORB_PATCH_PX = 31  # ORB's default patch


@dataclass(frozen=True)
class MonoParams:
    """Settings of the colour-only front end on top of `FrontEndParams`."""

    init_parallax_px: float = 20.0  # median corner displacement before trying two-view initialisation
    init_min_angle_deg: float = 5.0  # median triangulation angle of an accepted initialisation
    init_min_points: int = 60  # triangulated inliers needed to start
    init_refine_frames: int = 8  # frames between the two views in the initial bundle adjustment (0 = none)
    essential_px: float = 1.0  # RANSAC threshold of the essential matrix
    min_angle_deg: float = 2.0  # a track is triangulated once its rays differ this much
    max_reprojection_px: float = 2.0  # at every keyframe that observed it
    pending_max_keyframes: int = 10  # pending tracks older than this many keyframes are dropped
    keyframe_baseline_ratio: float = 0.06  # keyframe when translation / median landmark depth exceeds it
    retriangulate: bool = True  # live landmarks are re-triangulated from all their observations at each keyframe
    # Relocalisation after a loss: the landmarks of the last reloc_keyframes keyframes carry ORB descriptors
    # (computed at their tracked corners); a lost frame's corners are matched against them (ratio test) and
    # PnP places it in the map, so the map's scale is kept across the gap.
    reloc_keyframes: int = 8
    reloc_ratio: float = 0.85  # Lowe ratio of the descriptor matches
    reloc_pnp_px: float = 3.0  # PnP RANSAC threshold on descriptor matches (corners re-detected to ~1 px)
    reloc_max_hamming: int = 64  # of 256 bits
    # Keyframes after a relocalisation before a bundle adjustment of the re-entry (the keyframes since
    # reloc_keyframes before the gap, their landmarks; scale held by the keyframes before the gap). The
    # first keyframes after a gap stand on few landmarks and would pass a scale error on to the new ones.
    # Measured (8 blank frames, 640x480, seeds 11/12/13): ATE across the gap 0.067/0.121/0.093 % of the
    # path with it, 0.163/0.128/0.101 % without.
    reentry_ba_keyframes: int = 4
    # Guided search radius around the extrapolated pixel, of the image width: hand-held sway makes a constant-
    # velocity extrapolation over a 9-frame gap 2.5-7.7 deg off (simulated rows, true velocity).
    reloc_search_fraction: float = 0.25
    # Lost frames with texture that could not be relocalised are kept (greyscale) with the frames tracked after
    # a later relocalisation; at the re-entry bundle adjustment they are placed by tracking back from the
    # current frame, frame by frame. Seed 13 of the blank-frame test (8 blank frames): the first 6 frames
    # after the gap match too few landmarks to be placed on their own (a hedge's repetitive leaves behind
    # them), and the relocalised seventh has 38 tracks, too few to track back from; from the re-entry
    # keyframe's hundreds of tracks every one is placed. At most this many frames are kept.
    backtrack_max_frames: int = 60
    # The front end's own small bundle adjustments (the initial refinement, the re-entry after a loss), not the
    # side's (config section `ba`): a few keyframes each, converged tightly, every observation kept.
    ba_iterations: int = 20
    ba_relative_error_tol: float = 1e-5
    ba_max_track: int = 0


def triangulate(T_a: np.ndarray, xa: np.ndarray, T_b: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Linear (DLT) two-view triangulation in normalised coordinates.

    T_a, T_b: T_odom_cam (4, 4) or one per point (N, 4, 4); xa, xb: normalised image points (N, 2)
    (K^-1 applied). Returns odom points (N, 3), NaN for points at infinity.
    """
    rows = []
    for T, x in ((T_a, xa), (T_b, xb)):
        T = np.broadcast_to(T, (len(x), 4, 4))
        R = np.swapaxes(T[:, :3, :3], 1, 2)  # (N, 3, 3) odom -> cam
        P = np.concatenate([R, -R @ T[:, :3, 3:]], axis=2)  # (N, 3, 4)
        rows += [x[:, :1] * P[:, 2] - P[:, 0], x[:, 1:] * P[:, 2] - P[:, 1]]
    A = np.stack(rows, axis=1)  # (N, 4, 4)
    X = np.linalg.svd(A)[2][:, -1]  # (N, 4)
    w = X[:, 3:]
    return np.where(np.abs(w) > 1e-12, X[:, :3] / np.where(w == 0, 1.0, w), np.nan)


class RGBFrontEnd(MonoRelocalisation, RGBDFrontEnd):
    """Incremental colour-only odometry up to scale; feed frames with `track`, then `result()`."""

    requires_depth = False

    def __init__(self, intr: CameraIntrinsics, params: FrontEndParams = FrontEndParams(),
                 mono: MonoParams = MonoParams()) -> None:
        super().__init__(intr, params)
        self.m = mono
        # Pending tracks (corners not yet triangulated): pixel now, uid, first keyframe and pixel there.
        self._pend_pts = np.zeros((0, 2), np.float32)
        self._pend_uid = np.zeros(0, np.int64)
        self._pend_kf0 = np.zeros(0, np.int64)
        self._pend_uv0 = np.zeros((0, 2))
        self._next_uid = 0
        # Keyframe observations of pending tracks (kf, uid, uv): they become landmark observations.
        self._pobs_kf = np.zeros(0, np.int64)
        self._pobs_uid = np.zeros(0, np.int64)
        self._pobs_uv = np.zeros((0, 2))
        # Initialisation: reference frame, corners there and now, and their pixels in the frames between.
        self._ref: RGBDFrame | None = None
        self._ref_gray: np.ndarray | None = None
        self._ref_slot = 0  # position of the reference frame in self.poses
        self._init_uv0 = np.zeros((0, 2), np.float32)
        self._init_uv = np.zeros((0, 2), np.float32)
        self._init_hist: list[tuple[int, np.ndarray]] = []  # (slot in self.poses, pixels (N, 2))
        # When lost: (image, track pixels, landmark ids, pose, slot in self.poses) of the last tracked frame.
        self._last_good: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int] | None = None
        self._kf_slot: list[int] = []  # position in self.poses of each keyframe's frame
        self._reentry_kf: int | None = None  # keyframe made at the last relocalisation, until its re-entry BA
        # Lost frames that had texture but were not relocalised, (slot in self.poses, image), and the frames
        # tracked since the relocalisation that followed them: placed by tracking back at the re-entry.
        self._unplaced: list[tuple[int, np.ndarray, int]] = []  # (slot, image, frame index)
        self._since_reloc: list[tuple[int, np.ndarray, int]] = []
        # Upright BRIEF (angle 0) at given corners: descriptors of landmarks and of a lost frame's corners.
        self._orb = cv2.ORB_create(edgeThreshold=ORB_PATCH_PX // 2 + 1, patchSize=ORB_PATCH_PX)

    # -- geometry helpers

    def _normalised(self, uv: np.ndarray) -> np.ndarray:
        return (uv - [self.K.cx, self.K.cy]) / [self.K.fx, self.K.fy]

    def _rays(self, T: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Unit viewing rays (N, 3) in odom of pixels uv (N, 2) seen from T_odom_cam (4, 4) or (N, 4, 4)."""
        d = np.concatenate([self._normalised(uv), np.ones((len(uv), 1))], axis=1)
        d = np.einsum("nij,nj->ni", np.broadcast_to(T, (len(uv), 4, 4))[:, :3, :3], d)
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def _add_points(self, X: np.ndarray) -> np.ndarray:
        """Append triangulated landmarks X (N, 3) (unit weight: no depth to refine them with)."""
        start = len(self._lm_w)
        self._lm_sum = np.vstack([self._lm_sum, X])
        self._lm_w = np.concatenate([self._lm_w, np.ones(len(X))])
        return np.arange(start, start + len(X))

    def _median_depth(self, T: np.ndarray) -> float | None:
        if not len(self._ids):
            return None
        z = self._project(T, self.landmarks[self._ids])[1]
        z = z[z > 0]
        return float(np.median(z)) if len(z) else None

    # -- initialisation

    def _initialise(self, gray: np.ndarray, frame: RGBDFrame) -> np.ndarray | None:
        if self._ref is not None:
            tracked = self._klt(gray, self._init_uv, None)
            if tracked is not None:
                p1, good = tracked
                self._init_uv0, self._init_uv = self._init_uv0[good], p1[good]
                self._init_hist = [(slot, uv[good]) for slot, uv in self._init_hist]
            if tracked is not None and len(self._init_uv) >= self.m.init_min_points:
                pose = self._try_two_view(gray, frame)
                if pose is not None:
                    return pose
                self._init_hist.append((len(self.poses), self._init_uv.copy()))
                return None
            self.events.append(f"frame {frame.index}: initialisation lost its tracks; starting again here")
        corners = self._new_corners(gray, np.zeros((0, 2), np.float32))
        if len(corners) < self.m.init_min_points:
            self.events.append(f"frame {frame.index}: not enough texture to start; waiting")
            self._ref = None
            return None
        self._ref, self._ref_gray, self._ref_slot = frame, gray, len(self.poses)
        self._init_uv0, self._init_uv = corners.astype(np.float32), corners.astype(np.float32)
        self._init_hist = []
        return None

    def _try_two_view(self, gray: np.ndarray, frame: RGBDFrame) -> np.ndarray | None:
        uv0, uv1 = self._init_uv0.astype(np.float64), self._init_uv.astype(np.float64)
        if np.median(np.linalg.norm(uv1 - uv0, axis=1)) < self.m.init_parallax_px:
            return None
        E, inl = cv2.findEssentialMat(uv0, uv1, self.Kmat, cv2.RANSAC, 0.999, self.m.essential_px)
        if E is None or E.shape != (3, 3):
            return None
        _, R, t, inl = cv2.recoverPose(E, uv0, uv1, self.Kmat, mask=inl)
        T1 = np.eye(4)  # T_odom_cam of the current frame; odom = the reference camera, |t| = 1
        T1[:3, :3] = R.T
        T1[:3, 3] = -R.T @ t.ravel()
        X, ok, angle = self._triangulate_checked(np.eye(4), uv0, T1, uv1)
        ok &= inl.ravel() > 0
        if ok.sum() < self.m.init_min_points or np.median(angle[ok]) < self.m.init_min_angle_deg:
            return None
        if self.m.init_refine_frames:
            T1, X = self._refine_initial(uv0, uv1, T1, X, ok)
            X, ok2, angle = self._triangulate_checked(np.eye(4), uv0, T1, uv1, X)
            ok &= ok2
        lm = ok & (angle >= self.m.min_angle_deg / 2)  # low-parallax inliers wait as pending tracks
        ids = self._add_points(X[lm])
        self._add_keyframe(self._ref_gray, None, self._ref, np.eye(4), ids, uv0[lm], np.zeros(len(ids)))
        self._add_keyframe(gray, None, frame, T1, ids, uv1[lm], np.zeros(len(ids)))
        self._pts, self._ids = uv1[lm].astype(np.float32), ids
        self._pose = T1
        # The frames between: PnP on their tracked pixels (the reference frame is the origin).
        self.poses[self._ref_slot] = np.eye(4)
        for slot, uv in self._init_hist:
            pose, _ = self._pnp(self.landmarks[ids], uv[lm].astype(np.float64), None)
            if pose is not None:
                self.poses[slot] = pose
        pend = ok & ~lm
        self._start_pending(uv0[pend], 0, uv1[pend], 1)
        self._start_pending(self._new_corners(gray, np.vstack([self._pts, self._pend_pts])), 1)
        self.events.append(f"frame {frame.index}: initialised from frames {self._ref.index}-{frame.index} "
                           f"({len(ids)} landmarks, median angle {np.median(angle[ok]):.1f} deg, "
                           "unit = their baseline)")
        self._ref = self._ref_gray = None
        self._init_hist = []
        return T1

    def _refine_initial(self, uv0: np.ndarray, uv1: np.ndarray, T1: np.ndarray, X: np.ndarray, ok: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
        """Bundle adjustment of the two-view start over the reference, up to init_refine_frames frames
        between (their pose by PnP) and the current frame: a two-view estimate from a sideways motion
        confuses rotation with translation direction (a few degrees), which the map would inherit as
        a scale drift. Gauge as in RGB-only BA: reference fixed, its distance to the current frame kept (1).
        Returns the refined T_odom_cam of the current frame and points (N, 3) (NaN where not refined)."""
        idx = np.flatnonzero(ok)
        hist = self._init_hist[::max(1, -(-len(self._init_hist) // self.m.init_refine_frames))]
        poses, uvs = [np.eye(4)], [uv0[idx]]
        for _, uv in hist:
            pose, _ = self._pnp(X[idx], uv[idx].astype(np.float64), None)
            if pose is not None:
                poses.append(pose)
                uvs.append(uv[idx].astype(np.float64))
        poses.append(T1)
        uvs.append(uv1[idx])
        n = len(idx)
        obs = Observations(np.repeat(np.arange(len(uvs)), n), np.tile(np.arange(n), len(uvs)), np.vstack(uvs),
                           np.zeros(n * len(uvs)))
        try:
            ba = bundle_adjust(np.array(poses), X[idx], obs, self.K, mode="rgb", max_iterations=self.m.ba_iterations,
                               relative_error_tol=self.m.ba_relative_error_tol, max_track=self.m.ba_max_track)
        except ReconstructionError as e:  # keep the two-view estimate
            self.events.append(f"initial refinement failed ({e}); using the two-view estimate")
            return T1, X
        out = np.full_like(X, np.nan)
        out[idx] = ba.landmarks
        return ba.poses[-1], out

    def _triangulate_checked(self, Ta: np.ndarray, uva: np.ndarray, Tb: np.ndarray, uvb: np.ndarray,
                             X: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points (N, 3) from two views (or X given), whether they pass (in front, reprojection), angles (N,) deg."""
        if X is None:
            X = triangulate(Ta, self._normalised(uva), Tb, self._normalised(uvb))
        cosang = np.sum(self._rays(Ta, uva) * self._rays(Tb, uvb), axis=1)
        angle = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
        ok = np.all(np.isfinite(X), axis=1)
        for T, uv in ((Ta, uva), (Tb, uvb)):
            p, z = self._project(T, np.where(ok[:, None], X, 0.0))
            ok &= (z > 0) & (np.linalg.norm(p - uv, axis=1) < self.m.max_reprojection_px)
        return X, ok, angle

    # -- pending tracks

    def _start_pending(self, uv: np.ndarray, kf: int, uv_now: np.ndarray | None = None,
                       kf_now: int | None = None) -> None:
        """New pending tracks first seen at keyframe kf at uv (N, 2); optionally also seen at kf_now (uv_now)."""
        n = len(uv)
        uid = np.arange(self._next_uid, self._next_uid + n)
        self._next_uid += n
        now = uv if uv_now is None else uv_now
        self._pend_pts = np.vstack([self._pend_pts, now]).astype(np.float32)
        self._pend_uid = np.concatenate([self._pend_uid, uid])
        self._pend_kf0 = np.concatenate([self._pend_kf0, np.full(n, kf)])
        self._pend_uv0 = np.vstack([self._pend_uv0, uv])
        self._record_pending(np.full(n, kf), uid, uv)
        if uv_now is not None:
            self._record_pending(np.full(n, kf_now), uid, uv_now)

    def _record_pending(self, kf: np.ndarray, uid: np.ndarray, uv: np.ndarray) -> None:
        self._pobs_kf = np.concatenate([self._pobs_kf, kf])
        self._pobs_uid = np.concatenate([self._pobs_uid, uid])
        self._pobs_uv = np.vstack([self._pobs_uv, uv])

    def _keep_pending(self, keep: np.ndarray) -> None:
        self._pend_pts, self._pend_uid = self._pend_pts[keep], self._pend_uid[keep]
        self._pend_kf0, self._pend_uv0 = self._pend_kf0[keep], self._pend_uv0[keep]

    def _track_pending(self, gray: np.ndarray) -> None:
        """KLT of the pending tracks into `gray`, predicted at the live landmarks' median depth."""
        if not len(self._pend_pts):
            return
        guess = None
        last = self.poses[-1] if self.poses else None
        z = self._median_depth(last) if last is not None and np.isfinite(last).all() else None
        if z is not None:
            X = last[:3, 3] + self._rays(last, self._pend_pts.astype(np.float64)) * z  # ~ depth z (distance z)
            guess = self._predict(X, fallback=self._pend_pts)
        tracked = self._klt(gray, self._pend_pts, guess)
        if tracked is None:
            self._keep_pending(np.zeros(len(self._pend_pts), bool))
            return
        p1, good = tracked
        self._pend_pts = p1.astype(np.float32)
        self._keep_pending(good)

    def _triangulate_pending(self, kf: int) -> None:
        """Triangulate pending tracks with enough parallax since their first keyframe (kf = the current one)."""
        kf_poses = np.array([k.T_odom_cam for k in self.keyframes])
        T0, T1 = kf_poses[self._pend_kf0], kf_poses[kf]
        uv1 = self._pend_pts.astype(np.float64)
        X, ok, angle = self._triangulate_checked(T0, self._pend_uv0, T1, uv1)
        ripe = angle >= self.m.min_angle_deg
        # Every keyframe observation of a candidate must agree (catches tracks sliding along the epipolar line).
        cand = np.flatnonzero(ripe & ok)
        order = np.argsort(self._pend_uid[cand])
        sorted_uid = self._pend_uid[cand][order]
        rows = np.flatnonzero(np.isin(self._pobs_uid, sorted_uid))
        which = cand[order][np.searchsorted(sorted_uid, self._pobs_uid[rows])]  # pending index of each row
        p, z = self._project(kf_poses[self._pobs_kf[rows]], X[which])
        bad = (z <= 0) | (np.linalg.norm(p - self._pobs_uv[rows], axis=1) >= self.m.max_reprojection_px)
        ok[which[bad]] = False
        new = ripe & ok
        if new.any():
            ids = self._add_points(X[new])
            lm_of = np.full(len(new), -1)
            lm_of[new] = ids
            sel = lm_of[which] >= 0
            rows, lm_rows = rows[sel], lm_of[which[sel]]
            self._obs.append((self._pobs_kf[rows], lm_rows, self._pobs_uv[rows], np.zeros(len(rows))))
            self._pts = np.vstack([self._pts, self._pend_pts[new]]).astype(np.float32)
            self._ids = np.concatenate([self._ids, ids])
        # Triangulated tracks leave the pending set, so do failed ripe ones and those waiting too long.
        self._keep_pending(~ripe & (kf - self._pend_kf0 <= self.m.pending_max_keyframes))
        live = np.isin(self._pobs_uid, self._pend_uid)
        self._pobs_kf, self._pobs_uid, self._pobs_uv = self._pobs_kf[live], self._pobs_uid[live], self._pobs_uv[live]

    def _retriangulate(self) -> None:
        """Re-triangulate the live landmarks from all their keyframe observations (linear, multi-view)."""
        if not len(self._ids):
            return
        kf_all, lm_all, uv_all, _ = (np.concatenate(x) for x in zip(*self._obs, strict=True))
        rows = np.flatnonzero(np.isin(lm_all, self._ids))
        ids, inv, cnt = np.unique(lm_all[rows], return_inverse=True, return_counts=True)
        kf_poses = np.array([k.T_odom_cam for k in self.keyframes])
        T = kf_poses[kf_all[rows]]
        R = np.swapaxes(T[:, :3, :3], 1, 2)
        P = np.concatenate([R, -R @ T[:, :3, 3:]], axis=2)  # (n, 3, 4)
        x = self._normalised(uv_all[rows])
        A1 = x[:, :1] * P[:, 2] - P[:, 0]
        A2 = x[:, 1:] * P[:, 2] - P[:, 1]
        # Normal equations of the stacked DLT rows per landmark: sum of outer products (4x4), smallest eigenvector.
        M = np.zeros((len(ids), 4, 4))
        np.add.at(M, inv, A1[:, :, None] * A1[:, None, :] + A2[:, :, None] * A2[:, None, :])
        X = np.linalg.eigh(M)[1][:, :, 0]
        good = (cnt >= 3) & (np.abs(X[:, 3]) > 1e-12)
        Xc = X[:, :3] / np.where(np.abs(X[:, 3:]) > 1e-12, X[:, 3:], 1.0)
        p, z = self._project(T, Xc[inv])
        bad = (z <= 0) | (np.linalg.norm(p - uv_all[rows], axis=1) >= self.m.max_reprojection_px)
        good[inv[bad]] = False
        self._lm_sum[ids[good]] = Xc[good] * self._lm_w[ids[good], None]

    # -- overrides of the RGB-D front end

    def _track_klt(self, gray: np.ndarray, frame: RGBDFrame) -> np.ndarray | None:
        self._track_pending(gray)  # first: a keyframe made while tracking the landmarks triangulates them
        pose = super()._track_klt(gray, frame)
        if pose is not None and self._unplaced:
            self._since_reloc.append((len(self.poses), gray, frame.index))
            del self._since_reloc[:-self.m.backtrack_max_frames]
        return None if pose is None else self._pose  # a re-entry bundle adjustment may have moved it

    def _maybe_keyframe(self, gray: np.ndarray, frame: RGBDFrame, pose: np.ndarray) -> None:
        rel = np.linalg.inv(self._kf_pose) @ pose
        z = self._median_depth(pose)
        if (z is None or np.linalg.norm(rel[:3, 3]) > self.m.keyframe_baseline_ratio * z
                or pose_rotation_deg(rel) > self.p.keyframe_rotation_deg
                or len(self._pts) < self.p.keyframe_min_tracked):
            self._make_keyframe(gray, frame, pose)

    def _make_keyframe(self, gray: np.ndarray, frame: RGBDFrame, pose: np.ndarray, first: bool = False) -> bool:
        if first:  # one colour frame cannot seed a map (the RGB-D front end restarts this way)
            return False
        kf = len(self.keyframes)
        self._add_keyframe(gray, None, frame, pose, self._ids.copy(), self._pts.astype(np.float64),
                           np.zeros(len(self._ids)))
        self._record_pending(np.full(len(self._pend_uid), kf), self._pend_uid, self._pend_pts.astype(np.float64))
        if self.m.retriangulate:
            self._retriangulate()
        self._triangulate_pending(kf)
        self._start_pending(self._new_corners(gray, np.vstack([self._pts, self._pend_pts])).astype(np.float64), kf)
        if self._reentry_kf is not None and kf - self._reentry_kf >= self.m.reentry_ba_keyframes:
            self._reentry_bundle_adjustment()
            if self._unplaced:
                self._place_by_tracking_back(gray, len(self.poses), frame.index)
        return True

    def _lose_tracks(self) -> None:
        super()._lose_tracks()
        self._keep_pending(np.zeros(len(self._pend_uid), bool))
        self._pobs_kf, self._pobs_uid, self._pobs_uv = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))

    def _add_keyframe(self, gray: np.ndarray, depth: np.ndarray | None, frame: RGBDFrame, pose: np.ndarray,
                      ids: np.ndarray, uv: np.ndarray, z: np.ndarray) -> None:
        first_of_start = not self.keyframes and self._ref is not None  # the reference frame of initialisation
        self._kf_slot.append(self._ref_slot if first_of_start else len(self.poses))
        super()._add_keyframe(gray, depth, frame, pose, ids, uv, z)

    def _keyframe_features(self, gray: np.ndarray, depth: np.ndarray | None, pose: np.ndarray, ids: np.ndarray,
                           uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Colour-only keyframes carry descriptors of the landmarks they observe (at the tracked corners),
        so that a lost frame can be placed against the map (relocalisation keeps the map's scale)."""
        kp, des, lm = self._corner_descriptors(gray, uv, ids)
        return kp, des, np.zeros(len(kp), np.float32), lm

    def _corner_descriptors(self, gray: np.ndarray, uv: np.ndarray, ids: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Upright ORB descriptors at pixels uv (N, 2) tagged ids (N,): (uv, descriptors, ids) of those not
        too close to the border."""
        if not len(uv):
            kp, des, _ = no_keyframe_features()
            return kp, des, np.zeros(0, np.int64)
        kps = [cv2.KeyPoint(float(u), float(v), ORB_PATCH_PX, 0.0, 0.0, 0, i) for i, (u, v) in enumerate(uv)]
        kps, des = self._orb.compute(gray, kps)
        if des is None or not len(kps):
            kp, des, _ = no_keyframe_features()
            return kp, des, np.zeros(0, np.int64)
        keep = np.array([k.class_id for k in kps], np.int64)
        return np.asarray(uv, np.float32)[keep], des.astype(np.uint8), np.asarray(ids, np.int64)[keep]

    def result(self) -> FrontEndResult:
        if self._unplaced and self._since_reloc and self._lost_streak == 0:  # ended before the re-entry
            slot, gray, index = self._since_reloc[-1]
            self._place_by_tracking_back(gray, slot, index)
        if not self.keyframes:
            self.events.append("colour-only initialisation never succeeded (too little texture or parallax)")
        return super().result()
