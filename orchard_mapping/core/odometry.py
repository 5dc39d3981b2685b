"""Front end of single-side reconstruction: RGB-D visual odometry with keyframes.

The paper computes each consecutive pair's rigid transform with three-point
RANSAC on SIFT matches with valid depth, then refines it by pairwise BA. We
track corners with pyramidal Lucas-Kanade from frame to frame (cheaper than
matching descriptors in every frame, and long tracks give bundle adjustment
many observations per landmark) and estimate each frame's pose by RANSAC PnP
against landmarks seeded from keyframe depth: the same minimal three-point
RANSAC, against a map instead of the previous frame, which drifts less.
Landmark positions are refined at each keyframe by the inverse-variance
weighted mean of their depth back-projections (RealSense depth noise grows
with z^2), the pairwise-refinement step of the paper in closed form.

Hand-held motion breaks the constant-velocity prediction (a jerk of the
hand, a quick re-aim, a bump under a vehicle): KLT started tens of pixels
off with a small window and a shallow pyramid then loses most tracks, and a
pose from the few left can be centimetres off without any "loss". So when
fewer than `retrack_inlier_ratio` of the live tracks survive KLT and PnP,
the frame is tracked again coarse to fine: a deeper pyramid and larger
window from the constant-velocity and from the zero-velocity guess give a
pose, and the fine KLT started at that pose's pixels refines it. Measured on
the `tilted` scenario (2.5 deg hand jitter, 9 deg roll; 3 trees, 15 Hz, seed
7), front end alone: front side drift 5.99 -> 0.07 %, back 0.25 -> 0.13 %,
with 0 losses; on `standard` it never triggers (same poses, same time).

When tracking fails (blank frames, motion blur, a hand over the lens) the
front end re-localises against the last keyframes with ORB descriptors and
logs it, and tracks on from the relocalisation's inlier matches (see
_track_relocalised); frames it cannot place keep a NaN pose.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import cv2
import numpy as np

from orchard_mapping.core.keyframe_features import make_keyframe_features, no_keyframe_features
from orchard_mapping.core.sidemap import FrontEndResult, Keyframe, Observations
from orchard_mapping.core.types import CameraIntrinsics, RGBDFrame

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrontEndParams:
    """Front-end settings (config section `odometry`)."""

    __pydantic_config__ = {"extra": "forbid"}  # config files: unknown keys are errors

    max_corners: int = 700  # corners kept per keyframe (new ones fill empty image regions)
    corner_quality: float = 0.003  # relative to the strongest corner (foliage has low contrast)
    corner_min_distance_px: int = 10
    # px. Small windows hold less of the background that slides behind a leaf or trunk edge (a window
    # mixing both lags the foreground: systematic yaw drift). Measured, keyframes every 2.5 cm, after BA:
    # 10-tree standard front drift 0.31 -> 0.12 %, final rotation error 0.48 -> 0.14 deg (21 -> 11 px).
    klt_window_px: int = 11
    klt_levels: int = 2  # the constant-velocity prediction puts KLT near the answer: few levels suffice
    klt_iterations: int = 20
    klt_epsilon_px: float = 0.01  # LK stops when an update moves the point less than this
    klt_fb_max_px: float = 0.0  # forward-backward consistency check (0 = off: PnP RANSAC rejects outliers)
    pnp_reprojection_px: float = 2.0
    # Adaptive inlier gate (0 = off): after RANSAC at pnp_reprojection_px, the matches are re-scored with
    # the gate min(pnp_reprojection_px, max(pnp_min_reprojection_px, k * sigma)), sigma the inliers'
    # robust reprojection spread (median norm / 1.177, a 2D Gaussian's Rayleigh median; k = 3 holds 99 %
    # of it), and the pose refined on them. Leaves moving in the wind at 30 Hz stay inside a fixed 2 px
    # gate and bias the pose. Measured, front end alone, drift / ATE % of path, fixed 2 px -> k = 3:
    # 10-tree wind 30 Hz front 0.36/0.078 -> 0.17/0.036, back 0.41/0.115 -> 0.16/0.043; mean ATE of 12
    # hand-held and steady 3-tree sides (tilted 10/15/30 Hz, handheld_walk, slope_weeds 10 Hz,
    # standard) 0.028 -> 0.027 (10 better, 4 worse, largest loss standard back 0.025 -> 0.033).
    pnp_gate_sigmas: float = 3.0
    pnp_min_reprojection_px: float = 1.0
    pnp_iterations: int = 100
    min_inliers: int = 25  # fewer PnP inliers: tracking is lost
    # m. Dense keyframes (about every frame at 0.5 m/s, 15 Hz) give BA each landmark's whole track:
    # 10-tree standard front side, BA drift 0.52 -> 0.32 % and ATE 0.106 -> 0.072 % vs 0.08 m (the
    # slow yaw drift of sparse keyframes), at ~3x the BA time. Fusion cleans only every cleaned_spacing_m.
    keyframe_translation_m: float = 0.025
    keyframe_rotation_deg: float = 4.0
    keyframe_min_tracked: int = 250  # fewer live tracks: make a keyframe to seed new landmarks
    landmark_depth_max_m: float = 6.0  # the background rows (~4.6 m) still fix rotation; BA weights them by z^2
    depth_edge_m: float = 0.03  # reject depth whose edge window spans more than this (+ 5 sensor sd)
    # px, odd. A corner is very often where a trunk or leaf edge crosses texture: its KLT window (11 px)
    # then holds two surfaces that move differently (parallax), and its depth may be either one's or a
    # flying pixel's. Such landmarks bias the scale along the row. A 7x7 test keeps corners 3 px from any
    # depth edge. Measured, front end alone, 10 sides (loop 2 trees seed 12; standard, tilted 10 Hz,
    # handheld_walk, slope_weeds 10 Hz: 3 trees seed 7), mean ATE % of path: 3x3 0.087, 5x5 0.050,
    # 7x7 0.029 (lower on all 10 sides than 3x3, no losses); 9x9 starves some views of landmarks
    # (two sides at 0.23 and 0.32 %, relocalisations). The loop back side: drift 0.41 -> 0.15 %.
    depth_edge_window_px: int = 7
    # Of the corners whose window passes the edge test, this fraction with the most depth relief (plane-fit
    # residual RMS over the window, in units of the sensor's noise at that range) takes no depth. A small
    # step (leaf over leaf, a trunk edge over the ground behind it) hides under the edge test's noise
    # margin but still biases the scale along the row: front end alone, 10-tree standard (seed 0) and
    # handheld_walk (seed 3) sides, |scale error| mean 0.165 % with none dropped, 0.056 / 0.037 / 0.024 /
    # 0.025 % at 0.15 / 0.25 / 0.40 / 0.55; ATE 11.8 -> 5.2 mm at 0.40 (each of the 4 sides better; a
    # vehicle row never tuned on: ATE 9.1 / 12.5 -> 6.4 / 5.2 mm). A rank, not a threshold at some number
    # of noise sd: the residual of flat, noisy depth sits right at the noise, and a fixed threshold
    # (1 sd + 3 mm helped; 0.75 sd starved the tracker) would hinge on the sensor's noise being as set.
    depth_rough_drop_fraction: float = 0.4
    depth_sigma_coeff: float = 0.004  # sensor depth sd = coeff * z^2 (m), weights landmark refinement
    orb_features: int = 1000  # per keyframe, for relocalisation and loop detection
    # m / deg: keyframes carry ORB features (relocalisation, loop detection) only this far from the last
    # keyframe that has them. With a keyframe every frame, ORB + its depth check cost ~25 ms per frame.
    orb_keyframe_translation_m: float = 0.1
    orb_keyframe_rotation_deg: float = 4.0
    # New corners are searched (goodFeaturesToTrack, ~9 ms) only when at least this fraction of
    # max_corners is free: lost tracks are replaced in batches instead of one by one every frame.
    min_free_corner_fraction: float = 0.1
    restart_after_frames: int = 5  # lost this long with texture in view: restart at the extrapolated pose
    # Hand-held motion: when fewer than retrack_inlier_ratio of the live tracks survive KLT + PnP, the
    # frame is tracked again coarse to fine (a deeper pyramid and larger window from the constant- and the
    # zero-velocity guess, then the fine KLT from that pose). Steady motion never pays for it.
    retrack_inlier_ratio: float = 0.5
    retrack_levels: int = 4
    retrack_window_px: int = 21

    def __post_init__(self) -> None:
        if self.depth_edge_window_px < 3 or self.depth_edge_window_px % 2 == 0:
            raise ValueError(f"depth_edge_window_px must be odd and >= 3, got {self.depth_edge_window_px}")
        if not 0.0 <= self.depth_rough_drop_fraction < 1.0:
            raise ValueError(f"depth_rough_drop_fraction must be in [0, 1), got {self.depth_rough_drop_fraction}")


def backproject(uv: np.ndarray, z: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    """Pixels (N, 2) with depth (N,) -> camera-frame points (N, 3)."""
    x = (uv[:, 0] - intr.cx) / intr.fx * z
    y = (uv[:, 1] - intr.cy) / intr.fy * z
    return np.stack([x, y, z], axis=1)


def sample_depth(depth: np.ndarray, uv: np.ndarray, edge_m: float, sigma_coeff: float = 0.004,
                 edge_window_px: int = 7, rough_drop_fraction: float = 0.0) -> np.ndarray:
    """Depth (N,) at pixels uv (N, 2): median of the 3x3 window; 0 where missing or near a depth edge.

    A pixel is near an edge (where flying pixels live, and where a tracked corner may lie on another
    surface than its depth) when its edge_window_px square holds a missing value or spans more than
    edge_m plus five times the sensor noise at that range (sd = sigma_coeff * z^2). The 49 samples of a
    7x7 window of pure noise span 4.5 sd on average (more than 5 sd one time in five), so beyond ~4 m,
    where edge_m is small against the noise, some edge-free far points are dropped too.

    rough_drop_fraction: of the pixels that pass, this fraction with the most relief in their window
    (RMS off the window's least-squares plane, over 1 mm + the noise sd at that range) get 0 too: the
    small steps the edge test's noise margin lets through (FrontEndParams.depth_rough_drop_fraction).
    """
    h, w = depth.shape
    r = edge_window_px // 2
    iu = np.clip(np.round(uv[:, 0]).astype(int), r, w - 1 - r)
    iv = np.clip(np.round(uv[:, 1]).astype(int), r, h - 1 - r)
    # (N, k, k): one gather of each pixel's window (a stack of k*k gathers took twice as long)
    windows = np.lib.stride_tricks.sliding_window_view(depth, (edge_window_px, edge_window_px))[iv - r, iu - r]
    win = windows.reshape(len(iu), -1)  # (N, k*k), row-major
    centre = windows[:, r - 1:r + 2, r - 1:r + 2].reshape(-1, 9)  # (N, 9)
    z = np.median(centre, axis=1).astype(np.float64)
    valid = np.all(win > 0, axis=1) & (win.max(axis=1) - win.min(axis=1) < edge_m + 5 * sigma_coeff * z * z)
    if rough_drop_fraction > 0 and np.count_nonzero(valid) >= 8:
        rough = _plane_residual_rms(win[valid].astype(np.float64), edge_window_px) / (
            1e-3 + sigma_coeff * z[valid] ** 2)  # (V,) relief in noise sd
        keep = rough <= np.quantile(rough, 1.0 - rough_drop_fraction)
        valid[np.flatnonzero(valid)[~keep]] = False
    return np.where(valid, z, 0.0)


def _plane_residual_rms(win: np.ndarray, k: int) -> np.ndarray:
    """RMS (N,) m of each k x k depth window (N, k*k), row-major, off its least-squares plane."""
    dv, du = np.meshgrid(np.arange(k) - k // 2, np.arange(k) - k // 2, indexing="ij")
    A = np.stack([np.ones(k * k), du.ravel(), dv.ravel()], axis=1)  # (k*k, 3)
    fit = (win @ np.linalg.pinv(A).T) @ A.T  # (N, k*k)
    return np.sqrt(np.mean((win - fit) ** 2, axis=1))


def pose_from_rt(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """T_odom_cam from OpenCV's (rvec, tvec) = T_cam_odom."""
    R, _ = cv2.Rodrigues(rvec)
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ tvec.ravel()
    return T


def _rt_from_pose(T_odom_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    R = T_odom_cam[:3, :3].T
    t = -R @ T_odom_cam[:3, 3]
    return cv2.Rodrigues(R)[0], t.reshape(3, 1)


def pose_rotation_deg(T: np.ndarray) -> float:
    """Rotation angle (deg) of a pose or relative motion T (4, 4)."""
    return float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1))))


class RGBDFrontEnd:
    """Incremental RGB-D odometry; feed frames in order with `track`, then `result()`."""

    requires_depth = True  # the colour-only subclass (core/mono_odometry.py) ignores depth

    def __init__(self, intr: CameraIntrinsics, params: FrontEndParams = FrontEndParams()) -> None:
        self.K = intr
        self.Kmat = intr.K
        self.p = params
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        # Map: landmark positions (odom) with accumulated inverse-variance weights.
        self._lm_sum = np.zeros((0, 3))
        self._lm_w = np.zeros(0)
        # Live tracks in the previous frame.
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._prev_gray: np.ndarray | None = None
        self._pose: np.ndarray | None = None  # last good T_odom_cam
        self._kf_pose: np.ndarray | None = None
        self._orb_pose: np.ndarray | None = None  # pose of the last keyframe with ORB features
        self.keyframes: list[Keyframe] = []
        self._obs: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        self.stamps: list[float] = []
        self.poses: list[np.ndarray] = []
        self.events: list[str] = []
        self.lost_frames = 0
        self.retracked_frames = 0  # frames tracked again coarse to fine (see retrack_inlier_ratio)
        self._lost_streak = 0
        self._velocity = np.eye(4)  # last inter-frame motion, for extrapolating through lost stretches

    # -- map

    @property
    def landmarks(self) -> np.ndarray:  # (L, 3)
        return self._lm_sum / np.maximum(self._lm_w, 1e-12)[:, None]

    def _weight(self, z: np.ndarray) -> np.ndarray:
        sd = self.p.depth_sigma_coeff * z * z + 1e-3
        return 1.0 / sd ** 2

    def _add_landmarks(self, uv: np.ndarray, z: np.ndarray, T_odom_cam: np.ndarray) -> np.ndarray:
        pc = backproject(uv, z, self.K)
        pw = pc @ T_odom_cam[:3, :3].T + T_odom_cam[:3, 3]
        w = self._weight(z)
        start = len(self._lm_w)
        self._lm_sum = np.vstack([self._lm_sum, pw * w[:, None]])
        self._lm_w = np.concatenate([self._lm_w, w])
        return np.arange(start, start + len(z))

    def _refine_landmarks(self, ids: np.ndarray, uv: np.ndarray, z: np.ndarray, T_odom_cam: np.ndarray) -> None:
        ok = z > 0
        if not ok.any():
            return
        pc = backproject(uv[ok], z[ok], self.K)
        pw = pc @ T_odom_cam[:3, :3].T + T_odom_cam[:3, 3]
        w = self._weight(z[ok])
        np.add.at(self._lm_sum, ids[ok], pw * w[:, None])
        np.add.at(self._lm_w, ids[ok], w)

    # -- per frame

    def track(self, frame: RGBDFrame) -> np.ndarray:
        """Estimate T_odom_cam of `frame` (NaN if it cannot be placed); keyframes are kept internally."""
        if frame.depth is None and self.requires_depth:
            raise ValueError("RGBDFrontEnd needs depth; use the RGB-only front end for colour-only input")
        gray = cv2.cvtColor(frame.color, cv2.COLOR_RGB2GRAY)
        if self._pose is None:
            pose = self._initialise(gray, frame)
        else:
            pose = self._track_klt(gray, frame)
            if pose is None:
                pose = self._relocalise(gray, frame)
        if pose is not None:
            good = [p for p in self.poses[-1:] if np.isfinite(p).all()]
            if good and self._lost_streak == 0:
                self._velocity = np.linalg.inv(good[0]) @ pose
            self._lost_streak = 0
        else:
            self._lost_streak += 1
        self.stamps.append(frame.stamp)
        self.poses.append(pose if pose is not None else np.full((4, 4), np.nan))
        self._prev_gray = gray
        return self.poses[-1]

    def _initialise(self, gray: np.ndarray, frame: RGBDFrame) -> np.ndarray | None:
        pose = np.eye(4)
        if not self._make_keyframe(gray, frame, pose, first=True):
            self.events.append(f"frame {frame.index}: not enough texture or depth to start; waiting")
            return None
        self._pose = pose
        return pose

    def _track_klt(self, gray: np.ndarray, frame: RGBDFrame) -> np.ndarray | None:
        if len(self._pts) < self.p.min_inliers or self._prev_gray is None:
            return None
        # Constant-velocity prediction of where the tracked landmarks land: KLT starts there, so fast
        # motion (1 m/s, or a low frame rate) does not exceed the pyramid's capture range.
        X = self.landmarks[self._ids]
        guess = self._predict(X)
        best = self._track_from(gray, X, guess)
        if best is None or best[1].size < self.p.retrack_inlier_ratio * len(self._ids):
            # The prediction was far off (a jerk of the hand, a re-aim, a bump): the fine KLT lost many
            # tracks. Coarse KLT (deeper pyramid, larger window) from the constant-velocity and from the
            # zero-velocity guess gives a pose; fine KLT started at that pose's pixels refines it.
            for start in ([guess] if guess is not None else []) + [None]:
                coarse = self._track_from(gray, X, start, self.p.retrack_window_px, self.p.retrack_levels)
                if coarse is None:
                    continue
                fine = self._track_from(gray, X, self._project_pose(coarse[0], X))
                for cand in (fine, coarse):
                    if cand is not None and (best is None or cand[1].size > best[1].size):
                        best = cand
                if best[1].size >= self.p.retrack_inlier_ratio * len(self._ids):
                    break
            if best is not None:
                self.retracked_frames += 1
        if best is None:
            return None
        pose, inl, pts = best
        self._pts, self._ids = pts[inl].astype(np.float32), self._ids[inl]
        self._pose = pose
        self._maybe_keyframe(gray, frame, pose)
        return pose

    def _track_from(self, gray: np.ndarray, X: np.ndarray, guess: np.ndarray | None, window: int | None = None,
                    levels: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """KLT of the live tracks (landmarks X (N, 3)) from the previous frame into `gray`, started at `guess`
        (N, 2) (None: their previous pixels), then PnP: (pose, inlier rows (M,) of the live tracks, tracked
        pixels (N, 2)), or None."""
        tracked = self._klt(gray, self._pts, guess, window=window, levels=levels)
        if tracked is None:
            return None
        p1, good = tracked
        rows = np.flatnonzero(good)
        pose, inl = self._pnp(X[rows], p1[rows], self._pose)
        if pose is None:
            return None
        return pose, rows[inl], p1

    def _project(self, T: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixels (N, 2) and depths (N,) of odom points X (N, 3) seen from T_odom_cam (4, 4) or (N, 4, 4)."""
        T = np.broadcast_to(T, (len(X), 4, 4))
        pc = np.einsum("nji,nj->ni", T[:, :3, :3], X - T[:, :3, 3])
        z = pc[:, 2]
        zs = np.where(np.abs(z) > 1e-12, z, 1e-12)
        uv = np.stack([self.K.fx * pc[:, 0] / zs + self.K.cx, self.K.fy * pc[:, 1] / zs + self.K.cy], axis=1)
        return uv, z

    def _project_pose(self, T_odom_cam: np.ndarray, X: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of odom points X (N, 3) seen from T_odom_cam; behind the camera: the live tracks' pixels."""
        uv, z = self._project(T_odom_cam, X)
        return np.where((z > 0.05)[:, None], uv, self._pts)

    def _klt(self, gray: np.ndarray, pts: np.ndarray, guess: np.ndarray | None, prev: np.ndarray | None = None,
             levels: int | None = None, window: int | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """Track pixels pts (N, 2) from image `prev` (default: the previous frame's) into `gray`, starting at
        `guess` (N, 2) if given, with `levels` pyramid levels (default klt_levels) and a `window` px window
        (default klt_window_px).

        Returns the new positions (N, 2) and which were tracked inside the image (N,) bool; None if KLT failed."""
        prev = self._prev_gray if prev is None else prev
        win = self.p.klt_window_px if window is None else window
        lk = dict(winSize=(win, win),
                  maxLevel=self.p.klt_levels if levels is None else levels,
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, self.p.klt_iterations, self.p.klt_epsilon_px))
        p0 = pts.reshape(-1, 1, 2)
        flags = 0
        p1 = None
        if guess is not None:
            p1 = guess.reshape(-1, 1, 2).astype(np.float32)
            flags = cv2.OPTFLOW_USE_INITIAL_FLOW
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, gray, p0, p1, flags=flags, **lk)
        if p1 is None:
            return None
        good = st1.ravel() == 1
        if self.p.klt_fb_max_px > 0:
            p0b, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev, p1, None, **lk)
            fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
            good &= (st2.ravel() == 1) & (fb < self.p.klt_fb_max_px)
        h, w = gray.shape
        p1 = p1.reshape(-1, 2)
        good &= (p1[:, 0] >= 0) & (p1[:, 0] < w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] < h - 1)
        return p1, good

    def _predict(self, points: np.ndarray, fallback: np.ndarray | None = None) -> np.ndarray | None:
        """Pixels (N, 2) of odom points under a constant-velocity pose prediction, None if no motion history.

        Where the prediction puts a point behind the camera the pixel is taken from `fallback` (N, 2),
        by default the live tracks' previous positions."""
        if len(self.poses) < 2 or not np.isfinite(self.poses[-1]).all() or not np.isfinite(self.poses[-2]).all():
            return None
        last, prev = self.poses[-1], self.poses[-2]
        pred = last @ (np.linalg.inv(prev) @ last)
        rvec, tvec = _rt_from_pose(pred)
        proj, _ = cv2.projectPoints(points.astype(np.float64), rvec, tvec, self.Kmat, None)
        pc = (points - pred[:3, 3]) @ pred[:3, :3]
        proj = proj.reshape(-1, 2)
        # Keep the plain previous position where the prediction is behind the camera.
        return np.where((pc[:, 2] > 0.05)[:, None], proj, self._pts if fallback is None else fallback)

    def _pnp(self, obj: np.ndarray, img: np.ndarray, guess: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray]:
        if len(obj) < max(self.p.min_inliers, 6):
            return None, np.zeros(0, int)
        P, q = obj.astype(np.float64), img.astype(np.float64)  # (N, 3), (N, 2)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            P, q, self.Kmat, None, iterationsCount=self.p.pnp_iterations,
            reprojectionError=self.p.pnp_reprojection_px, confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        if not ok or inl is None or len(inl) < self.p.min_inliers:
            return None, np.zeros(0, int)

        def refine_and_score(subset: np.ndarray, rvec: np.ndarray, tvec: np.ndarray):
            """LM on the matches `subset`, then every match's reprojection error (N,) px with that pose."""
            rvec, tvec = cv2.solvePnPRefineLM(P[subset], q[subset], self.Kmat, None, rvec, tvec)
            proj, _ = cv2.projectPoints(P, rvec, tvec, self.Kmat, None)
            return rvec, tvec, np.linalg.norm(proj.reshape(-1, 2) - q, axis=1)

        # Re-score all matches with the refined pose (RANSAC's minimal-sample inlier set is noisy).
        rvec, tvec, err = refine_and_score(inl.ravel(), rvec, tvec)
        inl = np.flatnonzero(err < self.p.pnp_reprojection_px)
        if len(inl) < self.p.min_inliers:
            return None, np.zeros(0, int)
        if self.p.pnp_gate_sigmas > 0:
            sigma = float(np.median(err[inl])) / 1.177
            gate = min(self.p.pnp_reprojection_px, max(self.p.pnp_min_reprojection_px, self.p.pnp_gate_sigmas * sigma))
            tight = np.flatnonzero(err < gate)
            if gate < self.p.pnp_reprojection_px and len(tight) >= self.p.min_inliers:
                rvec, tvec, err = refine_and_score(tight, rvec, tvec)
                inl = np.flatnonzero(err < gate)
                if len(inl) < self.p.min_inliers:
                    inl = tight
        return pose_from_rt(rvec, tvec), inl

    def _maybe_keyframe(self, gray: np.ndarray, frame: RGBDFrame, pose: np.ndarray) -> None:
        rel = np.linalg.inv(self._kf_pose) @ pose
        if (np.linalg.norm(rel[:3, 3]) > self.p.keyframe_translation_m
                or pose_rotation_deg(rel) > self.p.keyframe_rotation_deg
                or len(self._pts) < self.p.keyframe_min_tracked):
            self._make_keyframe(gray, frame, pose)

    def _landmark_depth(self, depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """Depth (N,) a landmark may take at pixels uv (N, 2): 0 near a depth edge or beyond landmark_depth_max_m."""
        if not len(uv):
            return np.zeros(0)
        z = sample_depth(depth, uv.astype(np.float64), self.p.depth_edge_m, self.p.depth_sigma_coeff,
                         self.p.depth_edge_window_px, self.p.depth_rough_drop_fraction)
        return np.where(z <= self.p.landmark_depth_max_m, z, 0.0)

    def _make_keyframe(self, gray: np.ndarray, frame: RGBDFrame, pose: np.ndarray, first: bool = False) -> bool:
        depth = frame.depth
        assert depth is not None
        # Observations of the live tracks (with depth where valid), then landmark refinement.
        z_tr = self._landmark_depth(depth, self._pts)
        new_uv = self._new_corners(gray, self._pts)
        z_new = self._landmark_depth(depth, new_uv)
        keep = z_new > 0
        new_uv, z_new = new_uv[keep], z_new[keep]
        if first and len(new_uv) < self.p.min_inliers:
            return False
        if len(self._pts):
            self._refine_landmarks(self._ids, self._pts.astype(np.float64), z_tr, pose)
        new_ids = self._add_landmarks(new_uv.astype(np.float64), z_new, pose)
        uv_all = np.vstack([self._pts, new_uv]).astype(np.float64)
        ids_all = np.concatenate([self._ids, new_ids])
        z_all = np.concatenate([z_tr, z_new])
        self._pts = uv_all.astype(np.float32)
        self._ids = ids_all
        self._add_keyframe(gray, depth, frame, pose, ids_all, uv_all, z_all)
        return True

    def _new_corners(self, gray: np.ndarray, occupied: np.ndarray) -> np.ndarray:
        """Corners (N, 2) float32 away from the `occupied` pixels (M, 2), up to max_corners - M of them."""
        n_new = self.p.max_corners - len(occupied)
        new_uv = np.zeros((0, 2), np.float32)
        if n_new > 0 and n_new >= self.p.min_free_corner_fraction * self.p.max_corners:
            mask = np.full(gray.shape, 255, np.uint8)
            for u, v in occupied:
                cv2.circle(mask, (int(u), int(v)), self.p.corner_min_distance_px, 0, -1)
            c = cv2.goodFeaturesToTrack(gray, n_new, self.p.corner_quality, self.p.corner_min_distance_px, mask=mask)
            if c is not None:
                new_uv = c.reshape(-1, 2)
        return new_uv

    def _add_keyframe(self, gray: np.ndarray, depth: np.ndarray | None, frame: RGBDFrame, pose: np.ndarray,
                      ids: np.ndarray, uv: np.ndarray, z: np.ndarray) -> None:
        """Append keyframe `pose` with its landmark observations (ids, uv, z) and ORB features."""
        kf_id = len(self.keyframes)
        self._obs.append((np.full(len(ids), kf_id), ids, uv, z))
        kp_uv, desc, kp_z, kp_lm = self._keyframe_features(gray, depth, pose, ids, uv)
        self.keyframes.append(Keyframe(
            id=kf_id, frame_index=frame.index, stamp=frame.stamp, T_odom_cam=pose.copy(), keypoints=kp_uv,
            descriptors=desc, keypoint_depth=kp_z, keypoint_landmark=kp_lm))
        self._kf_pose = pose.copy()

    def _keyframe_features(self, gray: np.ndarray, depth: np.ndarray | None, pose: np.ndarray, ids: np.ndarray,
                           uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """ORB keypoints (N, 2), descriptors (N, 32), depth (N,) and landmark id (N,) (-1: none) of a new
        keyframe with pose `pose` that observes landmarks `ids` at pixels `uv`: RGB-D keyframes carry ORB
        features with depth (relocalisation, loop detection) only every orb_keyframe_* of motion."""
        rel = None if self._orb_pose is None else np.linalg.inv(self._orb_pose) @ pose
        if (rel is None or np.linalg.norm(rel[:3, 3]) >= self.p.orb_keyframe_translation_m
                or pose_rotation_deg(rel) >= self.p.orb_keyframe_rotation_deg):
            kp_uv, desc, kp_z = make_keyframe_features(gray, depth, n_features=self.p.orb_features)
            self._orb_pose = pose.copy()
        else:  # between ORB keyframes: tracks only
            kp_uv, desc, kp_z = no_keyframe_features()
        return kp_uv, desc, kp_z, np.full(len(kp_uv), -1, np.int64)

    def _lose_tracks(self) -> None:
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._orb_pose = None  # the keyframe made on recovery gets ORB features for the next relocalisation

    def _relocalise(self, gray: np.ndarray, frame: RGBDFrame) -> np.ndarray | None:
        """Lost: match ORB features of this frame against the latest keyframes and solve PnP.

        If that keeps failing while the frame has texture and depth, restart tracking at the pose
        extrapolated with the last known motion (the trajectory then has a seam that the log names).
        """
        self.lost_frames += 1
        self._lose_tracks()
        img_all, desc, _ = make_keyframe_features(gray, None, n_features=self.p.orb_features)
        if len(img_all) < self.p.min_inliers:
            self.events.append(f"frame {frame.index}: tracking lost (no texture)")
            return None
        img_all = img_all.astype(np.float64)
        for kf in itertools.islice((k for k in reversed(self.keyframes) if len(k.descriptors)), 3):
            pairs = self.matcher.knnMatch(kf.descriptors, desc, k=2)
            good = [m for m, *rest in pairs if rest and m.distance < 0.8 * rest[0].distance]
            qi = np.array([m.queryIdx for m in good], int)
            ti = np.array([m.trainIdx for m in good], int)
            obj, has_point = self._keyframe_points(kf, qi)
            img = img_all[ti[has_point]].reshape(-1, 2)
            pose, inl = self._pnp(obj, img, None)
            if pose is not None:
                self.events.append(f"frame {frame.index}: relocalised against keyframe {kf.id} ({len(inl)} inliers)")
                log.info(self.events[-1])
                self._pose = pose
                self._track_relocalised(obj[inl], img[inl], kf.keypoint_depth[qi[has_point]][inl])
                self._make_keyframe(gray, frame, pose)
                return pose
        if self._lost_streak + 1 >= self.p.restart_after_frames and self._pose is not None:
            steps = self._lost_streak + 1
            pose = self._pose.copy()
            for _ in range(steps):
                pose = pose @ self._velocity
            if self._make_keyframe(gray, frame, pose, first=True):
                self.events.append(f"frame {frame.index}: tracking restarted at the extrapolated pose after "
                                   f"{steps} lost frames (a seam in the trajectory)")
                log.warning(self.events[-1])
                self._pose = pose
                return pose
        self.events.append(f"frame {frame.index}: tracking lost, relocalisation failed")
        return None

    def _track_relocalised(self, X: np.ndarray, uv: np.ndarray, z: np.ndarray) -> None:
        """Live tracks of a relocalised frame: its relocalisation's PnP inliers, pixels uv (N, 2) of keyframe
        points X (N, 3) (odom) measured at depth z (N,) in that keyframe, become landmarks, one per cell of
        corner_min_distance_px (ORB finds one corner at several scales); the keyframe made next adds corners.

        The keyframe's corners alone are too few to track from: a corner takes landmark depth only where its
        7x7 window is complete, edge-free and not among the roughest (sample_depth), which a live track needs
        once in its life but a fresh map needs in a single frame. On the simulator's standard row 1 in 7 of
        the corners passes; with 5 % of the depth missing (camera.dropout 0.05) 13-22 of 700 do, under
        min_inliers, so every frame after a relocalisation was lost again and relocalised against the
        keyframe just made, while the ORB matches held 160-450 inliers."""
        cell = np.floor(uv / max(self.p.corner_min_distance_px, 1)).astype(np.int64)
        _, first = np.unique(cell[:, 0] * 100_000 + cell[:, 1], return_index=True)
        keep = np.sort(first)[: self.p.max_corners]
        w = self._weight(z[keep].astype(np.float64))
        start = len(self._lm_w)
        self._lm_sum = np.vstack([self._lm_sum, X[keep] * w[:, None]])
        self._lm_w = np.concatenate([self._lm_w, w])
        self._pts = uv[keep].astype(np.float32)
        self._ids = np.arange(start, start + len(keep))

    def _keyframe_points(self, kf: Keyframe, qi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Odom points (n, 3) of keyframe keypoints `qi` (N,) and which of them have one (N,) bool: valid depth."""
        ok = kf.keypoint_depth[qi] > 0
        pc = backproject(kf.keypoints[qi[ok]].astype(np.float64), kf.keypoint_depth[qi[ok]].astype(np.float64), self.K)
        return pc @ kf.T_odom_cam[:3, :3].T + kf.T_odom_cam[:3, 3], ok

    def result(self) -> FrontEndResult:
        if self._obs:
            kf, lm, uv, z = (np.concatenate(x) for x in zip(*self._obs, strict=True))
        else:
            kf, lm, uv, z = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0)
        return FrontEndResult(
            intrinsics=self.K, keyframes=list(self.keyframes), landmarks=self.landmarks,
            observations=Observations(kf.astype(np.int64), lm.astype(np.int64), uv, z),
            frame_stamps=np.array(self.stamps), frame_poses=np.array(self.poses).reshape(-1, 4, 4),
            events=list(self.events))
