"""Relocalisation of the colour-only front end (core.mono_odometry) after a loss: a lost frame's corners
matched against the recent keyframes' landmark descriptors (guided by the extrapolated pose, and unguided),
the PnP hypothesis grown to every landmark it predicts, the frames lost before the re-entry placed by
tracking back, and the re-entry bundle adjustment of the keyframes around the gap (module docstring of
core.mono_odometry, "Losses").

Frames: T_odom_cam (optical: x right, y down, z forward); the map's unit (up to scale); pixels in px.
"""

from __future__ import annotations

import cv2
import numpy as np

from orchard_mapping.core.bundle_adjustment import ReconstructionError, bundle_adjust
from orchard_mapping.core.odometry import pose_from_rt
from orchard_mapping.core.sidemap import Keyframe, Observations
from orchard_mapping.core.types import RGBDFrame


class MonoRelocalisation:
    """The relocalisation methods of `RGBFrontEnd` (a mixin: they use its state, `self.m`, `self.keyframes`,
    `self.landmarks`, `self.poses`, ..., and its `_corner_descriptors`)."""

    def _reentry_bundle_adjustment(self) -> None:
        """Bundle adjustment of the keyframes from reloc_keyframes before the re-entry keyframe to now and the
        landmarks they observe; keyframe 0 of the window and its distance to the last keyframe before the
        gap are held (the map's frame and scale). Keyframe poses, the frames between them (moved with their
        keyframe) and the landmarks are updated."""
        rec = self._reentry_kf
        self._reentry_kf = None
        first = max(0, rec - self.m.reloc_keyframes)
        if rec - first < 2:
            return
        kf_all, lm_all, uv_all, _ = (np.concatenate(x) for x in zip(*self._obs, strict=True))
        sel = kf_all >= first
        lm_ids, inv = np.unique(lm_all[sel], return_inverse=True)
        obs = Observations(kf_all[sel] - first, inv, uv_all[sel], np.zeros(int(sel.sum())))
        old = np.array([k.T_odom_cam for k in self.keyframes[first:]])
        try:
            ba = bundle_adjust(old, self.landmarks[lm_ids], obs, self.K, mode="rgb", max_iterations=self.m.ba_iterations,
                               relative_error_tol=self.m.ba_relative_error_tol, max_track=self.m.ba_max_track,
                               scale_anchor=rec - 1 - first)
        except ReconstructionError as e:
            self.events.append(f"re-entry bundle adjustment failed ({e}); keeping the tracked poses")
            return
        ok = np.isfinite(ba.landmarks).all(axis=1)
        self._lm_sum[lm_ids[ok]] = ba.landmarks[ok] * self._lm_w[lm_ids[ok], None]
        slots = self._kf_slot[first:] + [len(self.poses)]
        for i, k in enumerate(range(first, len(self.keyframes))):
            C = ba.poses[i] @ np.linalg.inv(old[i])  # correction of keyframe k, applied to the frames after it
            self.keyframes[k].T_odom_cam[:] = ba.poses[i]
            for slot in range(slots[i], slots[i + 1]):
                if np.isfinite(self.poses[slot]).all():
                    self.poses[slot] = C @ self.poses[slot]
        self._pose = C @ self._pose
        self._kf_pose = self.keyframes[-1].T_odom_cam.copy()

    def _keyframe_points(self, kf: Keyframe, qi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        lm = kf.keypoint_landmark[qi]
        ok = lm >= 0
        ok[ok] = np.isfinite(self.landmarks[lm[ok]]).all(axis=1)
        return self.landmarks[lm[ok]], ok

    def _relocalise(self, gray: np.ndarray, frame: RGBDFrame) -> np.ndarray | None:
        """Lost: place the frame against the map's recent landmarks by descriptor matching and PnP (guided
        by the pose extrapolated with the last motion, else unguided), gather every recent landmark that
        pose predicts in view, and re-track the last good frame's landmarks from there. Placing the frame
        against the map, not against a new two-view start, keeps the map's scale across the gap. A colour
        frame alone cannot seed a map, so there is no restart: a frame that cannot be placed stays lost."""
        if self._lost_streak == 0 and self._prev_gray is not None and len(self._pts):
            self._last_good = (self._prev_gray, self._pts.copy(), self._ids.copy(), self._pose.copy(),
                               len(self.poses) - 1)
        if self._since_reloc:  # lost again before the re-entry: the frames kept cannot be chained back
            self._unplaced, self._since_reloc = [], []
        self.lost_frames += 1
        self._lose_tracks()
        corners = self._lost_frame_corners(gray)
        if len(corners) < self.p.min_inliers:
            self.events.append(f"frame {frame.index}: tracking lost (no texture)")
            self._unplaced = []
            return None
        placed = self._relocalise_against_map(gray, corners)
        if placed is None:
            self.events.append(f"frame {frame.index}: tracking lost, relocalisation failed")
            self._unplaced.append((len(self.poses), gray, frame.index))
            del self._unplaced[:-self.m.backtrack_max_frames]
            return None
        pose, pts, ids = placed
        self._pts, self._ids, self._pose = pts, ids, pose
        steps = len(self.poses) - self._last_good[4] if self._last_good is not None else 0
        self.events.append(f"frame {frame.index}: tracking recovered: relocalised against the map "
                           f"({len(ids)} landmarks; last tracked frame {steps} frames back)")
        if self._unplaced:
            self._since_reloc = [(len(self.poses), gray, frame.index)]
        self._make_keyframe(gray, frame, pose)
        self._reentry_kf = len(self.keyframes) - 1
        return pose

    def _lost_frame_corners(self, gray: np.ndarray) -> np.ndarray:
        """Corners (C, 2) float32 of a frame to place without tracks: twice the tracker's count, half its spacing."""
        corners = cv2.goodFeaturesToTrack(gray, 2 * self.p.max_corners, self.p.corner_quality,
                                          max(2, self.p.corner_min_distance_px // 2))
        return np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2)

    def _place_by_tracking_back(self, gray: np.ndarray, slot: int, index: int) -> None:
        """Place the lost frames kept before the last relocalisation by tracking back from the frame at
        `slot` of self.poses (image `gray`, frame `index`; the live tracks and pose) through the frames since:
        KLT from each frame into the one before it, then PnP, until one fails. Their poses replace the NaN
        ones in self.poses."""
        chain = [f for f in self._since_reloc if f[0] < slot] + self._unplaced  # newest first after the sort
        chain.sort(key=lambda f: -f[0])
        self._unplaced, self._since_reloc = [], []
        if not chain or [f[0] for f in chain] != list(range(slot - 1, slot - 1 - len(chain), -1)):
            return  # not one unbroken run of frames up to `slot` (more were lost than were kept)
        pts, ids, pose, placed = self._pts, self._ids, self._pose, []
        lm, des, X = self._recent_landmark_descriptors()
        for older_slot, older, older_index in chain:
            tracked = self._klt(older, pts, None, prev=gray)
            best = None
            if tracked is not None:
                p1, good = tracked
                found, inl = self._pnp(self.landmarks[ids[good]], p1[good], pose)
                if found is not None:
                    best = found, p1[good][inl].astype(np.float32), ids[good][inl]
            if best is None or len(best[2]) < 2 * self.p.min_inliers:
                # Tracks thin out going back (occlusions at the leaves' edges): top them up from the recent
                # landmarks' descriptors and the last good frame's tracks, as relocalisation does.
                corners = self._lost_frame_corners(older)
                if len(corners) and len(lm):
                    uv, fdes, _ = self._corner_descriptors(older, corners, np.arange(len(corners)))
                    grown = self._grow_matches(older, best[0] if best else pose, lm, des, X, fdes, uv)
                    if grown is not None and (best is None or len(grown[2]) > len(best[2])):
                        best = grown
            if best is None:
                break
            pose, pts, ids = best
            if not np.isfinite(self.poses[older_slot]).all():
                self.poses[older_slot] = pose
                placed.append(older_index)
            gray = older
        if placed:
            self.events.append(f"frame {index}: {len(placed)} lost frames ({min(placed)}-{max(placed)}) placed by "
                               f"tracking back from it")

    def _predicted_pose(self) -> np.ndarray | None:
        """The last tracked pose extrapolated with the last motion to the current frame."""
        if self._last_good is None:
            return None
        pred = self._last_good[3].copy()
        for _ in range(len(self.poses) - self._last_good[4]):
            pred = pred @ self._velocity
        return pred

    def _relocalise_against_map(self, gray: np.ndarray, corners: np.ndarray
                                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(T_odom_cam, track pixels (N, 2) float32, landmark ids (N,)) of a lost frame with corners (C, 2).

        The landmarks seen by the last reloc_keyframes keyframes (each keyframe's descriptor) are matched to
        the corners' descriptors within reloc_search_fraction of the image width of their pixel under the
        extrapolated pose, and over the whole image; the match set whose PnP has more inliers wins. Then
        every such landmark is matched again within 2 reloc_pnp_px of its pixel under that pose, the last
        good frame's tracks are re-tracked by KLT started there, and a last PnP keeps the inliers."""
        lm, des, X = self._recent_landmark_descriptors()
        uv, fdes, _ = self._corner_descriptors(gray, corners, np.arange(len(corners)))
        if len(uv) < self.p.min_inliers or len(lm) < self.p.min_inliers:
            return None
        # Pose hypotheses: matches guided by the extrapolated pose, and unguided ones. Each is expanded to all
        # recent landmarks it predicts in view plus the last good frame's tracks; the largest consensus wins
        # (a pose from a few far background points can be metres off along the view yet fit them).
        best = None
        pred = self._predicted_pose()
        for guide in ((pred,) if pred is not None else ()) + (None,):
            q, t = self._match_descriptors(lm, des, X, fdes, uv, guide, self.m.reloc_search_fraction * self.K.width)
            pose, _ = self._pnp_matches(X[q], uv[t], self.m.reloc_pnp_px)
            if pose is None:
                continue
            for _ in range(2):  # the expanded consensus refines the pose, which finds more matches
                grown = self._grow_matches(gray, pose, lm, des, X, fdes, uv)
                if grown is None:
                    break
                pose = grown[0]
                if best is None or len(grown[2]) > len(best[2]):
                    best = grown
        return best

    def _recent_landmark_descriptors(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Landmark ids (L,), descriptors (L, 32) and odom points (L, 3) of the landmarks the last
        reloc_keyframes keyframes observed, a row per keyframe that saw one (its look changes along the row)."""
        kfs = [k for k in self.keyframes[-self.m.reloc_keyframes:][::-1] if len(k.descriptors)]
        if not kfs:
            return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8), np.zeros((0, 3))
        lm = np.concatenate([k.keypoint_landmark for k in kfs])
        des = np.vstack([k.descriptors for k in kfs])
        X = self.landmarks[lm]
        finite = np.isfinite(X).all(axis=1)
        return lm[finite], des[finite], X[finite]

    def _grow_matches(self, gray: np.ndarray, pose: np.ndarray, lm: np.ndarray, des: np.ndarray, X: np.ndarray,
                      fdes: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Descriptor matches of every recent landmark within 2 reloc_pnp_px of its pixel under `pose`, and the
        last good frame's tracks re-tracked by KLT (deeper pyramid) started there, then PnP:
        (pose, track pixels (N, 2) float32, landmark ids (N,)) or None."""
        q, t = self._match_descriptors(lm, des, X, fdes, uv, pose, 2 * self.m.reloc_pnp_px)
        img, ids = uv[t].astype(np.float64), lm[q]
        if self._last_good is not None:
            prev_gray, pts, lg_ids, _, _ = self._last_good
            guess, z = self._project(pose, self.landmarks[lg_ids])
            tracked = self._klt(gray, pts, np.where((z > 0)[:, None], guess, pts), prev=prev_gray,
                                levels=self.p.klt_levels + 2)
            if tracked is not None:
                p1, good = tracked
                keep = ~np.isin(ids, lg_ids[good])  # KLT's subpixel positions where both have the landmark
                img = np.vstack([img[keep], p1[good]])
                ids = np.concatenate([ids[keep], lg_ids[good]])
        pose, inl = self._pnp(self.landmarks[ids], img, None)
        if pose is None:
            return None
        return pose, img[inl].astype(np.float32), ids[inl]

    def _match_descriptors(self, lm: np.ndarray, des: np.ndarray, X: np.ndarray, fdes: np.ndarray, uv: np.ndarray,
                           pose: np.ndarray | None, radius: float | None) -> tuple[np.ndarray, np.ndarray]:
        """Ratio-test matches (rows, corner rows) of descriptors des (L, 32) of landmarks lm (L,) at odom points
        X (L, 3) to corner descriptors fdes (C, 32) at pixels uv (C, 2), one per landmark and corner; with a
        pose, only corners within `radius` px of the landmark's predicted pixel compete."""
        mask = None
        if pose is not None:
            pix, z = self._project(pose, X)
            d2 = np.sum((pix[:, None, :] - uv[None, :, :]) ** 2, axis=2)  # (L, C)
            mask = ((d2 <= radius * radius) & (z > 0)[:, None]).astype(np.uint8)
        pairs = self.matcher.knnMatch(des, fdes, k=2, mask=mask) if mask is None or mask.any() else []
        q, t = [], []
        for match in pairs:
            if not match:
                continue
            if len(match) == 1 or match[0].distance < self.m.reloc_ratio * match[1].distance:
                if match[0].distance <= self.m.reloc_max_hamming:
                    q.append(match[0].queryIdx)
                    t.append(match[0].trainIdx)
        q, t = np.array(q, int), np.array(t, int)
        # A landmark has a descriptor per keyframe: one pair per (landmark, corner), else PnP counts it twice.
        _, once = np.unique(np.stack([lm[q], t]), axis=1, return_index=True)
        return q[np.sort(once)], t[np.sort(once)]

    def _pnp_matches(self, obj: np.ndarray, img: np.ndarray, px: float) -> tuple[np.ndarray | None, np.ndarray]:
        """RANSAC PnP (AP3P, then LM on the inliers) of 3D-2D matches at threshold px: pose and inliers."""
        if len(obj) < max(self.p.min_inliers, 6):
            return None, np.zeros(0, int)
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj.astype(np.float64), img.astype(np.float64), self.Kmat, None,
                                                 iterationsCount=500, reprojectionError=px, confidence=0.999,
                                                 flags=cv2.SOLVEPNP_AP3P)
        if not ok or inl is None or len(inl) < self.p.min_inliers:
            return None, np.zeros(0, int)
        inl = inl.ravel()
        rvec, tvec = cv2.solvePnPRefineLM(obj[inl].astype(np.float64), img[inl].astype(np.float64), self.Kmat,
                                          None, rvec, tvec)
        return pose_from_rt(rvec, tvec), inl
