"""What one side keeps of its keyframes for trunk modelling: the trunk detections made beside the front end
(`EarlyDetections`), the trunk and post views fusion keeps as it comes to them (`TrunkViews`, `fuse_keyframes`),
and the views made from the geometry of the fused cloud's columns (`add_column_views`)."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, replace

import numpy as np

from orchard_mapping.config import OrchardConfig
from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK
from orchard_mapping.core.fusion import FusionResult, Region, fuse_side
from orchard_mapping.core.geometric_trunks import (
    column_detections,
    columns_to_model,
    detection_places,
    find_trunk_candidates,
    mask_place,
    on_tree_column,
)
from orchard_mapping.core.geometry import keyframes_every
from orchard_mapping.core.trunks import TrunkView
from orchard_mapping.core.types import CameraIntrinsics, ImagePatch, RGBDFrame, mask_bounds
from orchard_mapping.pipeline.sides import KeyframeImages
from orchard_mapping.pipeline.trunks import Detect, PostView, trunk_detector

log = logging.getLogger(__name__)


# px: a kept view holds its depth and masks this far around its trunk detections' boxes: the silhouette
# terms look 8 px outside a mask and move its edges by up to trunks.edge_snap_px (core/cylinder.py).
VIEW_MARGIN_PX = 24


class EarlyDetections:
    """Trunk detection beside the front end: each keyframe trunks.detect_every_m on from the last (by the front
    end's poses) goes to the detector on a thread of its own as the keyframe is made. The front end is mostly
    Python on one core and onnxruntime lets go of the GIL, so the detector uses the other: on the 10-tree
    standard row this hid most of its ~4 s per side, which it took after bundle adjustment before. Masks are
    kept as the part of the frame around them."""

    def __init__(self, cfg: OrchardConfig, side: str, detect: Detect | None = None) -> None:
        self.detect = detect or trunk_detector(cfg, side)
        self.spacing_m = cfg.trunks.detect_every_m
        self.seconds = 0.0  # s in the detector
        self._last: np.ndarray | None = None
        self._worker = ThreadPoolExecutor(1, thread_name_prefix=f"trunk-detector-{side}")
        self._pending: dict[int, Future] = {}  # frame index -> its detections, on their way

    def offer(self, keyframe, frame: RGBDFrame) -> None:
        """A keyframe (core.sidemap.Keyframe) just made from `frame`: detect on it if it is far enough on."""
        c = keyframe.T_odom_cam[:3, 3]
        if not np.all(np.isfinite(c)) or (self._last is not None
                                            and np.linalg.norm(c - self._last) < self.spacing_m - 1e-6):
            return
        self._last = c
        self._pending[keyframe.frame_index] = self._worker.submit(self._detect, frame.color, frame.stamp)

    def _detect(self, color: np.ndarray, stamp: float) -> list | None:
        t0 = time.perf_counter()
        found = self.detect(color, stamp)
        self.seconds += time.perf_counter() - t0
        if found is None:
            return None
        masks = [np.asarray(d.mask, bool) for d in found]
        return [replace(d, mask=ImagePatch.crop(m, mask_bounds(m))) for d, m in zip(found, masks, strict=True)]

    def results(self) -> dict[int, list | None]:
        """Frame index -> detections (None: the detector did not answer), once all are in; the thread is let go."""
        try:
            return {fi: f.result() for fi, f in self._pending.items()}
        finally:
            self._worker.shutdown(wait=True, cancel_futures=True)


class TrunkViews:
    """Takes the detections made beside the front end (`EarlyDetections`) as fusion comes to their keyframes
    (`select`), keeps each post detection with the raw depth around it (fitted in `fit_posts`), and keeps what
    trunk modelling and the two-side diameter need of each keyframe with a trunk detection (`__call__`): pose,
    detections, and depth and masks cropped around the detections (ImagePatch). The depth is the raw one
    (trunks.view_depth "raw", the default), or the cleaned one ("cleaned"): then fusion cleans only these
    keyframes (a third to a half of them on the simulated rows; cleaning was most of fusion's time). Frames are
    dropped as they go: memory grows with the trunks seen, not with the row's frames."""

    def __init__(self, cfg: OrchardConfig, stamps: np.ndarray, poses: np.ndarray, intr: CameraIntrinsics,
                 detections: dict[int, list | None], frame_index: list[int]) -> None:
        self.cfg, self.stamps, self.poses, self.intr = cfg, stamps, poses, intr
        # frame index -> the detections made beside the front end; keyframe k's frame index
        self.detections, self.frame_index = detections, frame_index
        self.unavailable: list[int] = []  # keyframes the detector could not answer for
        self.views: list[TrunkView] = []
        # keyframe -> its trunk detections and the part of the frame around them, until it is cleaned
        self._detections: dict[int, tuple[list, Region]] = {}
        self.post_views: list[PostView] = []  # each post detection, fitted in model_trunks
        self._up = -poses[0][:3, 1] if len(poses) else np.array([0.0, -1.0, 0.0])  # odom: the first camera's up

    def select(self, k: int, color: np.ndarray, depth: np.ndarray | None = None) -> bool | Region:
        """Keyframe k, if the detector saw it: its posts kept with the raw depth around them, and the part of it
        fusion is to clean (the rows and columns around its trunk detections, as `__call__` crops them), or
        False."""
        fi = self.frame_index[k]
        if fi not in self.detections:
            return False
        found = self.detections[fi]
        if found is None:
            self.unavailable.append(k)
            return False
        if depth is not None and self.cfg.semantic_ba.use_posts:
            # A post is fitted from this frame's raw depth (model_trunks), so a frame with posts only is not
            # cleaned. The fit reads the depth inside the (eroded) mask: the mask's box is all that is kept.
            up_cam = self.poses[k][:3, :3].T @ self._up
            for d in found:
                if d.class_id == CLASS_POST:
                    mask = np.asarray(d.mask, bool)
                    box = mask_bounds(mask)
                    self.post_views.append(PostView(k, up_cam, ImagePatch.crop(depth, box), ImagePatch.crop(mask, box)))
        dets = [d for d in found if d.class_id == CLASS_TRUNK]
        if not dets:
            return False
        boxes = np.array([d.box for d in dets])  # (D, 4) x1 y1 x2 y2 px
        m = VIEW_MARGIN_PX + self.cfg.trunks.edge_snap_px
        rect = (int(np.floor(boxes[:, 1].min())) - m, int(np.floor(boxes[:, 0].min())) - m,
                int(np.ceil(boxes[:, 3].max())) + m, int(np.ceil(boxes[:, 2].max())) + m)
        self._detections[k] = (dets, rect)
        if self.cfg.trunks.view_depth == "raw" and depth is not None:
            # the view reads the raw depth: kept now, and nothing is cleaned (trunks.view_depth)
            self(k, np.where(depth <= self.cfg.fusion.depth_max_m, depth, np.float32(0.0)), None)
            return False
        return rect

    def __call__(self, k: int, depth: np.ndarray, color: np.ndarray | None) -> None:
        """Keep what trunk modelling needs of keyframe k (called by `select` with its raw depth, or by fusion with
        its cleaned depth after `select` chose it)."""
        dets, rect = self._detections.pop(k)
        dets = [replace(d, mask=ImagePatch.crop(np.asarray(d.mask, bool), rect)) for d in dets]
        self.views.append(TrunkView(k, float(self.stamps[k]), self.poses[k], ImagePatch.crop(depth, rect), dets))


def add_column_views(views: TrunkViews, points: np.ndarray, poses: np.ndarray, stamps: np.ndarray,
                     frame_index: list[int], images: KeyframeImages, intr: CameraIntrinsics, cfg: OrchardConfig) -> int:
    """Trunk views from geometry (trunks.geometric, core.geometric_trunks): the vertical round columns of the
    fused cloud on the row line that the detector missed ("fill"; with "only" every column, the detector's trunk
    views dropped) become trunk detections in the keyframes trunks.detect_every_m apart that see them (their
    depth read again from `images`: only when there is such a column). Returns the detections added."""
    tp = cfg.trunks
    candidates = find_trunk_candidates(points, poses)
    if tp.geometric == "only":
        views.views.clear()
    # A post detection on a column that tapers or branches is a trunk the detector took for a post (its look
    # unlike the training trunks'): it is not fitted as a post, and the column is modelled as a trunk below.
    kept = [pv for pv in views.post_views
            if not on_tree_column(mask_place(pv.mask, pv.depth, poses[pv.keyframe], intr), candidates)]
    if len(kept) < len(views.post_views):
        log.info("%d post detections lie on columns shaped as trunks (tapering or branching): not posts",
                 len(views.post_views) - len(kept))
        views.post_views[:] = kept
    # And a trunk detection on a post-like column (straight, untapered, bare to 1.4 m) is a post taken for a trunk.
    n_trunk = sum(len(v.detections) for v in views.views)
    views.views[:] = [v for v in (replace(v, detections=[d for d in v.detections if not on_tree_column(
        mask_place(d.mask, v.depth, v.T_odom_cam, intr), candidates, post_like=True)]) for v in views.views)
        if v.detections]
    dropped = n_trunk - sum(len(v.detections) for v in views.views)
    if dropped:
        log.info("%d trunk detections lie on columns shaped as posts (straight, untapered, bare): not trunks", dropped)
    todo = columns_to_model(candidates, detection_places(views.views, intr), tp.min_observations,
                            tp.associate_radius_m, only=tp.geometric == "only")
    if not todo:
        return 0
    picks = {frame_index[k]: k for k in keyframes_every(poses, tp.detect_every_m)}  # frame index -> keyframe
    added = 0
    for fi, depth, _ in images.frames(sorted(picks)):
        k = picks[fi]
        depth = np.where(depth <= cfg.fusion.depth_max_m, depth, np.float32(0.0))
        dets = column_detections(todo, depth, poses[k], intr, cfg.odometry.depth_sigma_coeff, tp.min_mask_pixels,
                                 cfg.fusion.depth_max_m)
        if not dets:
            continue
        m = VIEW_MARGIN_PX + tp.edge_snap_px
        boxes = np.array([d.box for d in dets])  # (D, 4) x1 y1 x2 y2 px
        rect = (int(boxes[:, 1].min()) - m, int(boxes[:, 0].min()) - m, int(boxes[:, 3].max()) + m,
                int(boxes[:, 2].max()) + m)
        views.views.append(TrunkView(k, float(stamps[k]), poses[k], ImagePatch.crop(depth, rect),
                                     [replace(d, mask=ImagePatch.crop(d.mask, rect)) for d in dets]))
        added += len(dets)
    return added


def fuse_keyframes(images: KeyframeImages, frame_index: list[int], poses: np.ndarray, intr, cfg: OrchardConfig,
                   views: TrunkViews, tap: Callable[[int, np.ndarray, np.ndarray], None] | None = None
                   ) -> FusionResult:
    """TSDF fusion of the keyframes' depth (frame_index[k] is keyframe k's frame) with their optimised poses
    (k, 4, 4); the keyframes with a trunk detection go to `views` as fusion comes to them (cleaned as fusion moves
    on, with trunks.view_depth "cleaned"). tap: also called with each keyframe (k, raw depth, colour) as fusion
    reads it (the fruit stage: no second pass over the images)."""
    pose_of = dict(zip(frame_index, poses, strict=True))
    k_of = {fi: k for k, fi in enumerate(frame_index)}

    def frames() -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        for i, depth, color in images.frames(sorted(pose_of)):
            if tap is not None:
                tap(k_of[i], depth, color)
            yield depth, color, pose_of[i]

    return fuse_side(frames(), intr, keyframes=None, on_cleaned=views, select=views.select, **asdict(cfg.fusion))
