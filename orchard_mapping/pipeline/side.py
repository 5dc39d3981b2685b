"""The offline pipeline: bags in, result folder out (docs/results.md). One public `run()`.

Reads as the paper's steps, per side: front end (RGB-D odometry with
keyframes), loop detection, pose graph, bundle adjustment, TSDF fusion, trunk
detection with trunk cylinders and local grounds; then writes each side's
trajectory, cloud, trunks and grounds.
"""

from __future__ import annotations

import ctypes
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Protocol

import numpy as np

from orchard_mapping.config import OrchardConfig, dump_yaml
from orchard_mapping.core.alignment import AlignmentSide, SideAlignment, align_sides, icp_merge, pair_trunks
from orchard_mapping.core.bundle_adjustment import BAResult, bundle_adjust_windowed, optimise_pose_graph
from orchard_mapping.core.cylinder import Cylinder, CylinderError, fit_cylinders_shared_radius
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
from orchard_mapping.core.geometry import SlabIndex, matrix_to_quat, move_with_keyframes
from orchard_mapping.core.merge import HeightPrior, InitialTransform, SemanticPair, initial_transform
from orchard_mapping.core.odometry import RGBDFrontEnd
from orchard_mapping.core.posts import build_post_landmarks, fit_post_view, post_shapes, separate_trunks_from_posts
from orchard_mapping.core.semantic_ba import (
    HeightAnchor,
    SemanticBAResult,
    SideShapes,
    TrunkShape,
    semantic_bundle_adjust,
    trunk_frame,
)
from orchard_mapping.core.sidemap import FrontEndResult, LoopClosure, SideMap
from orchard_mapping.core.sides import UTurnSides
from orchard_mapping.core.trunks import (
    TrunkLandmark,
    TrunkParams,
    TrunkView,
    build_trunk_landmarks,
    ground_around_trunk,
)
from orchard_mapping.core.types import CameraIntrinsics, ImagePatch, RGBDFrame, StampedTrajectory, mask_bounds
from orchard_mapping.errors import AlignmentError, BagError, BagFormatError, MergeRefusedError
from orchard_mapping.io.bags import RGBDSequence, read_rgbd
from orchard_mapping.io.figures import RowView, write_row_png
from orchard_mapping.io.landmarks import GROUNDS_JSON, TRUNKS_JSON, write_grounds, write_trunks
from orchard_mapping.io.results import (
    SIDE_MERGE_JSON,
    TREES_CSV,
    TREES_JSON,
    ResultTree,
    atomic_write_text,
    map_trajectory_filename,
    write_side_merge,
    write_timings,
    write_trees,
    write_tum,
)

log = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]
SIDES = ("front", "back")


@dataclass
class Timings:
    stages: dict[str, float] = field(default_factory=dict)  # s per stage
    frames: int = 0
    recording_duration_s: float = 0.0
    # s, the run's wall clock (stages overlap: the detector's thread, the trunk worker); None until it is over
    wall_s: float | None = None

    def add(self, stage: str, seconds: float) -> None:
        self.stages[stage] = self.stages.get(stage, 0.0) + seconds


# What a merge writes into the result folder (docs/results.md).
MERGED_PLY, ROW_PNG = "merged.ply", "row.png"
MERGE_OUTPUTS = (SIDE_MERGE_JSON, TREES_JSON, TREES_CSV, map_trajectory_filename("*"), MERGED_PLY, ROW_PNG)


@dataclass(frozen=True)
class RunResult:
    out_dir: Path
    sides: dict[str, SideMap]
    timings: Timings
    merge_refused: str | None = None  # why the sides were not merged (run raises MergeRefusedError)


DRIVE = "drive"  # open_sides' key for one bag whose sides come from the camera's trajectory


def open_sides(front: Path, back: Path | None, cfg: OrchardConfig) -> dict[str, RGBDSequence]:
    """Two bags (front, back), or one bag whose side topic labels the frames, or (key DRIVE) one bag whose
    sides the camera's U-turn tells (input.side_source)."""
    inp = cfg.input
    kw = dict(mode=inp.mode, max_pair_dt_s=inp.max_pair_dt_s, depth_min_m=inp.depth_min_m, depth_max_m=inp.depth_max_m)
    if back is not None:
        if Path(front).resolve() == Path(back).resolve():
            raise BagError("the front and the back bag are the same file: a merge needs one recording of "
                           "each side of the row", bag=str(back))
        seqs = {"front": read_rgbd(front, inp.topics, **kw), "back": read_rgbd(back, inp.topics, **kw)}
        if np.array_equal(seqs["front"].stamps, seqs["back"].stamps):
            # a copy of one recording: merged with itself, a side would be mirrored onto the other
            raise BagError(f"the front and the back bag hold the same recording (the same "
                           f"{len(seqs['front'].stamps)} frame stamps as {front}): a merge needs one "
                           "recording of each side of the row", bag=str(back))
        return seqs
    seq = read_rgbd(front, inp.topics, **kw)
    labels = set(seq.sides) - {""}
    if inp.side_source == "trajectory" or (inp.side_source == "auto" and not labels):
        return {DRIVE: seq}  # the sides come from the camera's U-turn (reconstruct_drive)
    if not labels:
        raise BagFormatError("a single bag needs the side topic to tell front from back (input.side_source: "
                             "topic); no labels found", bag=str(front), topic=inp.topics.side)
    return {side: seq for side in SIDES if side in labels}


def _side_mask(seq: RGBDSequence, side: str) -> np.ndarray:
    """(N,) bool: the frames of a single-bag recording labelled `side` by the side topic."""
    return np.asarray(seq.sides, dtype=str) == side


def _frames_of(seq: RGBDSequence, side: str, labelled: bool) -> Iterator[RGBDFrame]:
    for f in seq:
        if not labelled or seq.sides[f.index] == side:
            yield f


def _new_front_end(intr, cfg: OrchardConfig):
    from orchard_mapping.core.mono_odometry import RGBFrontEnd  # colour only: landmarks by triangulation, up to scale

    return (RGBFrontEnd if cfg.input.mode == "rgb" else RGBDFrontEnd)(intr, cfg.odometry)


def front_end(frames, intr, cfg: OrchardConfig, progress: Progress | None, label: str, n: int) -> FrontEndResult:
    fe = _new_front_end(intr, cfg)
    for i, frame in enumerate(frames):
        fe.track(frame)
        if progress:
            progress(label, i + 1, n)
    for event in fe.events:
        log.warning("%s: %s", label, event)
    return fe.result()


class KeyframeImages(Protocol):
    """Where a side's keyframe images wait for fusion, which runs after bundle adjustment."""

    def keep(self, frame: RGBDFrame) -> None:
        """Called with each frame the front end makes a keyframe of, as it is made."""

    def frames(self, frame_index: list[int]) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(frame index, depth (H, W) float32 m, colour (H, W, 3) uint8) of these frames (ascending), in order."""

    def close(self) -> None:
        """Let go of what is kept."""


class BagKeyframeImages:
    """Offline: fusion reads the keyframes' images from the bag again (a second pass); nothing is kept."""

    def __init__(self, seq: RGBDSequence, side: str, labelled: bool) -> None:
        self.seq, self.side, self.labelled = seq, side, labelled

    def keep(self, frame: RGBDFrame) -> None:
        pass

    def frames(self, frame_index: list[int]) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        want = set(frame_index)
        for f in _frames_of(self.seq, self.side, self.labelled):
            if f.index in want and f.depth is not None:
                yield f.index, f.depth, f.color

    def close(self) -> None:
        pass


class SpooledKeyframeImages:
    """Live: each keyframe's depth and colour are written to a temporary folder as the keyframe is made
    (~2 MB at 640x480, a few keyframes per second) and read back, unchanged, for fusion: memory does not
    grow with the row, and fusion sees exactly what a second pass over the bag would give."""

    def __init__(self, root: str | Path | None = None) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="orchard-keyframes-", dir=root))

    def _paths(self, index: int) -> tuple[Path, Path]:
        return self.dir / f"{index:08d}_depth.npy", self.dir / f"{index:08d}_color.npy"

    def keep(self, frame: RGBDFrame) -> None:
        if frame.depth is None:
            return
        depth, color = self._paths(frame.index)
        np.save(depth, np.asarray(frame.depth, np.float32))
        np.save(color, np.asarray(frame.color, np.uint8))

    def frames(self, frame_index: list[int]) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        for i in frame_index:
            depth, color = self._paths(i)
            if depth.is_file():
                yield i, np.load(depth), np.load(color)

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


class SideSession:
    """One side's reconstruction fed a frame at a time: `add` runs the front end on each frame as it comes
    (from a bag, or from the camera topics in the live odometry node) and hands keyframes to the trunk
    detector's thread, `finish` does the rest once the side is over (loop detection, pose graph, bundle
    adjustment, TSDF fusion, trunk cylinders and local grounds). `orchard-map run` and the node graph go
    through this same class, so the same frames give the same side map."""

    def __init__(self, side: str, intrinsics, cfg: OrchardConfig, images: KeyframeImages, bag: str = "",
                 detect: Detect | None = None) -> None:
        self.side, self.intrinsics, self.cfg, self.images, self.bag = side, intrinsics, cfg, images, bag
        self.fe = _new_front_end(intrinsics, cfg)
        self.frames = 0
        self.seconds = 0.0  # s spent in the front end
        # trunk detection on a thread beside the front end, as keyframes are made; detect: None for the
        # configured detector in this process (trunk_detector())
        self.early = (EarlyDetections(cfg, side, detect)
                      if cfg.trunks.source != "off" and cfg.input.mode == "rgbd" else None)

    def add(self, frame: RGBDFrame) -> tuple[np.ndarray, bool]:
        """Track one frame: (T_odom_cam (4, 4), NaN when it could not be placed; whether it became a keyframe)."""
        t0 = time.perf_counter()
        n = len(self.fe.keyframes)
        pose = self.fe.track(frame)
        new = len(self.fe.keyframes) > n
        if new:
            self.images.keep(frame)
            if self.early is not None:
                self.early.offer(self.fe.keyframes[-1], frame)
        self.frames += 1
        self.seconds += time.perf_counter() - t0
        return pose, new

    def handover(self) -> "SideHandover":
        """What finishing the side needs, without the front end's live state (it pickles: the live odometry
        node finishes a side in another process)."""
        early = self.early.results() if self.early is not None else {}
        return SideHandover(self.side, self.intrinsics, self.cfg, self.images, self.bag, self.fe.result(),
                            list(self.fe.events), self.frames, self.seconds, early,
                            self.early.seconds if self.early is not None else 0.0)

    def finish(self, timings: Timings) -> SideMap:
        """Everything after the front end; the side map. Lets go of the kept keyframe images."""
        return self.finish_later(timings, None)()

    def finish_later(self, timings: Timings, worker: "TrunkWorker | None", here: bool = False) -> "PendingSide":
        """`finish` with the trunk modelling handed to `worker` (None, or here=True: done here); the side map once
        called. The worker's waiting jobs (an earlier side's) start now that this side's front end is over."""
        try:
            job = self.handover()
            if worker is not None:
                worker.start()
            return finish_side_later(job, timings, worker, here)
        finally:
            self.images.close()


@dataclass(frozen=True)
class SideHandover:
    """A side's front end done: what `finish_side` makes the side map from."""

    side: str
    intrinsics: CameraIntrinsics
    cfg: OrchardConfig
    images: KeyframeImages
    bag: str
    front_end: FrontEndResult
    events: list[str]
    frames: int  # frames tracked
    seconds: float  # s spent in the front end
    # frame index -> its trunk detections (None: the detector did not answer), for the keyframes the detector
    # was given beside the front end (EarlyDetections); empty without trunks
    detections: "dict[int, list | None]" = field(default_factory=dict)
    detection_seconds: float = 0.0  # s the detector took


# The disparity sd the bundle adjustment should assume, per px of its disparity residuals' robust sd, and how far
# above ba.disparity_sigma that must be before the run says so. 10-tree standard row, each side's drift: white
# depth noise (residuals 0.05 px): 0.5 px best (1.0: 36 -> 45 mm); noise in 6 px patches at twice the sd
# (0.19 px), back / front: 93 / 58 mm at 0.5, 66 / 53 at 1.0, 41 / 42 at 2.0; 4 px patches (0.10 px): 25 / 38 mm at 0.5,
# 19 / 44 at 1.0, no gain, hence the margin (docs/front_end.md).
DISPARITY_SIGMA_PER_RESIDUAL_SD = 10.0
DISPARITY_HINT_RATIO = 3.0


def finish_side_geometry(job: SideHandover, timings: Timings) -> tuple[SideMap, "TrunkJob | None"]:
    """Loop detection, pose graph, bundle adjustment, TSDF fusion (cleaning the keyframes with a trunk
    detection, with trunks.view_depth "cleaned"): the side map without its trunks and posts, and what modelling
    them needs (None: nothing to model)."""
    cfg, side, intr = job.cfg, job.side, job.intrinsics
    timings.add(f"front_end_{side}", job.seconds)
    for event in job.events:
        log.warning("%s: %s", side, event)
    fe = job.front_end
    if len(fe.keyframes) < 2:
        raise BagFormatError(f"the {side} side could not be reconstructed: {len(fe.keyframes)} keyframe(s) "
                             f"from {job.frames} frames (too little texture or valid depth)", bag=job.bag)
    poses = np.array([k.T_odom_cam for k in fe.keyframes])
    odometry = poses.copy()
    loops: list[LoopClosure] = []
    if cfg.loop.enabled and cfg.input.mode == "rgbd":
        t0 = time.perf_counter()
        loops = cfg.loop.detector(intr).detect_all(fe.keyframes)
        timings.add(f"loop_detection_{side}", time.perf_counter() - t0)
        log.info("%s: %d verified loop closures", side, len(loops))
    t0 = time.perf_counter()
    poses = optimise_pose_graph(poses, loops, loop_sigma_rot_deg=cfg.ba.loop_sigma_rot_deg,
                                loop_sigma_trans_m=cfg.ba.loop_sigma_trans_m)
    timings.add(f"pose_graph_{side}", time.perf_counter() - t0)
    t0 = time.perf_counter()
    ba: BAResult = bundle_adjust_windowed(poses, fe.landmarks, fe.observations, intr, mode=cfg.input.mode,
                                          loops=loops, **asdict(cfg.ba))
    timings.add(f"bundle_adjustment_{side}", time.perf_counter() - t0)
    release_freed_memory()
    log.info("%s: %d keyframes, %d landmarks used, BA error %.1f -> %.1f in %d iterations; disparity residuals' "
             "sd %.3f px (weighted as %.3f px)", side, len(fe.keyframes), ba.n_landmarks_used, ba.initial_error,
             ba.final_error, ba.iterations, ba.disparity_residual_sd, cfg.ba.disparity_sigma)
    suggested = DISPARITY_SIGMA_PER_RESIDUAL_SD * ba.disparity_residual_sd
    if np.isfinite(suggested) and suggested > DISPARITY_HINT_RATIO * cfg.ba.disparity_sigma:
        log.warning("%s: the depth is noisier than ba.disparity_sigma (%.2f px) assumes: its residuals spread %.3f px. "
                    "On simulated rows with such depth, ba.disparity_sigma of about %g times that (--set "
                    "ba.disparity_sigma=%.1f) cut each side's drift by a quarter to a half (docs/front_end.md)", side,
                    cfg.ba.disparity_sigma, ba.disparity_residual_sd, DISPARITY_SIGMA_PER_RESIDUAL_SD, suggested)
    points = np.zeros((0, 3), np.float32)
    colors = np.zeros((0, 3), np.uint8)
    stamps = np.array([k.stamp for k in fe.keyframes])
    trunk_job: TrunkJob | None = None
    if cfg.input.mode == "rgbd":
        t0 = time.perf_counter()
        frame_index = [k.frame_index for k in fe.keyframes]
        views = TrunkViews(cfg, stamps, ba.poses, intr, job.detections, frame_index)
        fused = fuse_keyframes(job.images, frame_index, ba.poses, intr, cfg, views)
        points, colors = fused.points, fused.colors
        timings.add(f"fusion_{side}", time.perf_counter() - t0)
        if cfg.trunks.source != "off" and cfg.trunks.geometric != "off":
            t0 = time.perf_counter()
            n_columns = add_column_views(views, points, ba.poses, stamps, frame_index, job.images, intr, cfg)
            timings.add(f"geometric_trunks_{side}", time.perf_counter() - t0)
            if n_columns:
                log.info("%s: %d trunk views made from the geometry of columns the detector %s", side, n_columns,
                         "was not asked about" if cfg.trunks.geometric == "only" else "missed")
        # the detector ran beside the front end: its time overlaps the front end's stage
        timings.add(f"trunk_detection_{side}", job.detection_seconds)
        if views.post_views or cfg.trunks.source != "off":
            trunk_job = TrunkJob(side, points, ba.poses, stamps, views.views, views.post_views, views.unavailable,
                                 intr, cfg)
    release_freed_memory()
    side_map = SideMap(
        side=side, frame_id=getattr(cfg.frames, f"odom_{side}"), intrinsics=intr,
        keyframe_stamps=stamps, keyframe_poses=ba.poses,
        landmarks=ba.landmarks, observations=fe.observations, loops=loops,
        cloud_points=points, cloud_colors=colors,
        scale_free=cfg.input.mode == "rgb",
        odometry_poses=odometry,
    )
    return side_map, trunk_job


@dataclass(frozen=True)
class TrunkJob:
    """What modelling one side's trunks and posts needs once its cloud is fused. It pickles: `orchard-map run`
    models a side's trunks in a worker process (TrunkWorker) while the next side is finished."""

    side: str
    points: np.ndarray  # (P, 3) float32 fused cloud, odom
    poses: np.ndarray  # (K, 4, 4) bundle-adjusted T_odom_cam
    stamps: np.ndarray  # (K,) s
    views: list[TrunkView]  # the keyframes with a trunk detection
    post_views: list[PostView]  # each post detection, with the raw depth around it
    unavailable: list[int]  # keyframes the detector could not answer for
    intrinsics: CameraIntrinsics
    cfg: OrchardConfig


@dataclass(frozen=True)
class TrunkModel:
    """One side's trunk and post landmarks (`model_trunks`), with what is to be logged and timed of them."""

    trunks: list[TrunkLandmark]
    posts: list
    warnings: list[str]  # each to be logged for the side
    info: list[str]
    seconds: dict[str, float]  # stage -> s


@dataclass(frozen=True)
class PostModel:
    """One side's post landmarks (`fit_posts`)."""

    posts: list
    views: int  # post views that gave a fit
    seconds: float


def fit_posts(job: TrunkJob) -> PostModel:
    """Each post view's own fit from its raw depth (RANSAC and the Huber refit reject stray pixels, so a post
    needs no cleaned depth), grouped into post landmarks. Reads neither the cloud nor the trunk views."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(job.cfg.seed)
    fits = [fit_post_view(np.asarray(v.depth), np.asarray(v.mask), job.intrinsics, v.up_cam, v.keyframe, rng)
            for v in job.post_views]
    fits = [f for f in fits if f is not None]
    posts = build_post_landmarks(fits, job.poses) if fits else []
    return PostModel(posts, len(fits), time.perf_counter() - t0)


def model_trunks(job: TrunkJob, post_model: "Callable[[], PostModel] | None" = None) -> TrunkModel:
    """Post landmarks from the post views, trunk landmarks with their local grounds from the fused cloud and the
    trunk views; a trunk that is a post is set aside. Pure: the same job gives the same model in any process.
    post_model: the posts fitted elsewhere (called once the trunks are modelled), instead of here first."""
    cfg, side = job.cfg, job.side
    seconds: dict[str, float] = {}
    warnings: list[str] = []
    info: list[str] = []
    trunks: list[TrunkLandmark] = []
    posts: list = []

    def take_posts(pm: PostModel) -> list:
        seconds[f"posts_{side}"] = pm.seconds
        info.append(f"{len(pm.posts)} trellis posts from {pm.views} post views")
        return pm.posts

    if job.post_views and post_model is None:
        posts = take_posts(fit_posts(job))
    if cfg.trunks.source != "off":
        t0 = time.perf_counter()
        trunks = build_trunk_landmarks(job.points, job.poses, job.views, job.intrinsics, cfg.trunks, cfg.ground,
                                       np.random.default_rng(cfg.seed))
        for t in trunks:
            if t.observations and all(o.detection.source == "geometry" for o in t.observations):
                t.flags.append(FOUND_BY_GEOMETRY)
        if job.post_views and post_model is not None:
            posts = take_posts(post_model())
        if posts:
            trunks, posts, said = separate_trunks_from_posts(trunks, posts, job.poses)
            warnings += said
        seconds[f"trunks_{side}"] = time.perf_counter() - t0
        if not trunks:
            warnings.append("no trunk found (trunks.json lists none for this side)")
        if job.unavailable:
            flag_trunks_near(trunks, job.poses[job.unavailable, :3, 3], cfg.fusion.depth_max_m)
            warnings.append(f"the trunk detector did not answer for {len(job.unavailable)} keyframes "
                            f"({job.stamps[job.unavailable[0]]:.1f}-{job.stamps[job.unavailable[-1]]:.1f} s): trees "
                            f"there may be missing; {sum(DETECTOR_UNAVAILABLE in t.flags for t in trunks)} trunks near "
                            "them are flagged")
    return TrunkModel(trunks, posts, warnings, info, seconds)


def with_trunks(side_map: SideMap, model: TrunkModel, timings: Timings) -> SideMap:
    """The side map with its trunks and posts; what modelling them said is logged, its time added."""
    for line in model.info:
        log.info("%s: %s", side_map.side, line)
    for line in model.warnings:
        log.warning("%s: %s", side_map.side, line)
    for stage, seconds in model.seconds.items():
        timings.add(stage, seconds)
    return replace(side_map, trunks=model.trunks, posts=model.posts)


def finish_side(job: SideHandover, timings: Timings) -> SideMap:
    """Loop detection, pose graph, bundle adjustment, TSDF fusion (cleaning the keyframes with a trunk
    detection, with trunks.view_depth "cleaned"), trunk cylinders and local grounds: the side map."""
    return finish_side_later(job, timings, None)()


PendingSide = Callable[[], SideMap]

# trunk flag: every view of it was made from the geometry of a column (trunks.geometric), none by the detector
FOUND_BY_GEOMETRY = "found_by_geometry"


def finish_side_later(job: SideHandover, timings: Timings, worker: "TrunkWorker | None",
                      here: bool = False) -> PendingSide:
    """finish_side with its trunk modelling handed to `worker` (None: done here): the side map once called.
    here=True: the trunks are modelled here and the posts in `worker` meanwhile (its process is idle by then:
    an earlier side's job ran beside this side's bundle adjustment)."""
    side_map, trunk_job = finish_side_geometry(job, timings)
    if trunk_job is None:
        return lambda: side_map
    if worker is None or here:
        post_model = None
        if worker is not None and trunk_job.post_views:
            posts_job = replace(trunk_job, points=np.zeros((0, 3), np.float32), views=[])  # what fit_posts reads
            future = worker.submit(fit_posts, posts_job)
            worker.start()
            post_model = lambda: worker.result(future, fit_posts, posts_job)  # noqa: E731
        side_map = with_trunks(side_map, model_trunks(trunk_job, post_model), timings)
        return lambda: side_map
    future = worker.submit(model_trunks, trunk_job)
    return lambda: with_trunks(side_map, worker.result(future, model_trunks, trunk_job), timings)


class TrunkWorker:
    """A process that models a side's trunks (`model_trunks`) while the main process finishes the next side.

    The run is mostly Python on one core. While a side's front end runs, the trunk detector's thread takes much
    of the other core; after it (loop detection, bundle adjustment: one core) the other core is idle. So a job
    waits (`submit`) until the next side's front end is over (`start`), and only then is the process spawned
    (its imports take ~1.5 s): on the 10-tree standard row, the same work run beside the front end slowed the
    front end and the detector by as much as it saved. Spawned, not forked: the main process holds
    onnxruntime's threads. If the worker dies, the side's trunks are modelled here instead."""

    def __init__(self) -> None:
        self._pool = None
        self._waiting: list[tuple[Callable, TrunkJob | BandPair, Future]] = []

    def submit(self, fn: Callable, job: "TrunkJob | BandPair") -> Future:
        """fn(job) (model_trunks, fit_posts, two_side_diameter), once `start` has sent it to the process and the
        process is done with it."""
        future: Future = Future()
        self._waiting.append((fn, job, future))
        return future

    @property
    def spawned(self) -> bool:
        """Whether the process is up (spawning one costs ~1.5 s of imports before it can help)."""
        return self._pool is not None

    def start(self) -> None:
        """Send the waiting jobs to the process (spawned now, if it is not yet)."""
        if not self._waiting:
            return
        if self._pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        for fn, job, future in self._waiting:
            self._pool.submit(fn, job).add_done_callback(lambda f, out=future: _pass_on(f, out))
        self._waiting = []

    def result(self, future: Future, fn: Callable, job: "TrunkJob | BandPair"):
        """What `submit(fn, job)` gave; fn(job) run here if the process died."""
        from concurrent.futures.process import BrokenProcessPool

        self.start()
        try:
            return future.result()
        except BrokenProcessPool as err:
            log.warning("the trunk worker process stopped (%s); %s runs here instead", err, fn.__name__)
            return fn(job)

    def close(self) -> None:
        for _, _, future in self._waiting:
            future.cancel()
        self._waiting = []
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)


def _pass_on(done: Future, out: Future) -> None:
    """Hand a finished future's outcome on to another future."""
    if done.cancelled():
        out.cancel()
    elif done.exception() is not None:
        out.set_exception(done.exception())
    else:
        out.set_result(done.result())


def reconstruct_side(seq: RGBDSequence, side: str, cfg: OrchardConfig, timings: Timings, labelled: bool = False,
                     progress: Progress | None = None) -> SideMap:
    """One side of a bag through a `SideSession` (fusion reads the keyframes' images from the bag again)."""
    return reconstruct_side_later(seq, side, cfg, timings, labelled, progress, None)()


def reconstruct_side_later(seq: RGBDSequence, side: str, cfg: OrchardConfig, timings: Timings, labelled: bool,
                           progress: Progress | None, worker: "TrunkWorker | None", here: bool = False) -> "PendingSide":
    """`reconstruct_side` with the side's trunk modelling handed to `worker` (None, or here=True: done here;
    `worker` still starts an earlier side's job once this side's front end is over)."""
    n = int(np.sum(_side_mask(seq, side))) if labelled else len(seq)
    session = SideSession(side, seq.intrinsics, cfg, BagKeyframeImages(seq, side, labelled), bag=seq.bag)
    t0 = time.perf_counter()
    for i, frame in enumerate(_frames_of(seq, side, labelled)):
        session.add(frame)
        if progress:
            progress(side, i + 1, n)
    session.seconds = time.perf_counter() - t0  # the front end's stage includes decoding the bag's images
    return session.finish_later(timings, worker, here)


def reconstruct_drive(seq: RGBDSequence, cfg: OrchardConfig, timings: Timings,
                      progress: Progress | None = None, worker: "TrunkWorker | None" = None) -> dict[str, SideMap]:
    """One continuous drive round a row without side labels: each frame tracked by its side's `SideSession`,
    the side changing half way round the U-turn (core.sides.UTurnSides), as the live odometry node does."""
    turns = UTurnSides()
    sessions: dict[str, SideSession] = {}
    session: SideSession | None = None
    seconds: dict[str, float] = {}
    for i, frame in enumerate(seq):
        if session is None:
            if turns.side in sessions:
                raise BagFormatError(f"the drive turns back to the {turns.side} side at frame {i} ({frame.stamp:.3f} s): "
                                     "one bag holds one drive round one row (front, U-turn, back)", bag=seq.bag)
            session = sessions[turns.side] = SideSession(turns.side, seq.intrinsics, cfg,
                                                         BagKeyframeImages(seq, turns.side, False), bag=seq.bag)
            t0 = time.perf_counter()
        pose, _ = session.add(frame)
        if turns.update(pose):
            seconds[session.side] = time.perf_counter() - t0
            session = None
        if progress:
            progress("drive", i + 1, len(seq))
    if session is not None:
        seconds[session.side] = time.perf_counter() - t0
    log.info("drive: %s", ", ".join(f"{side} {s.frames} frames" for side, s in sessions.items()))
    pending = {}
    last = list(sessions)[-1]
    for side, s in sessions.items():
        s.seconds = seconds[side]  # the front end's stage includes decoding the bag's images
        # a side's trunks are modelled in the worker while the next side is finished
        pending[side] = s.finish_later(timings, worker, here=side == last)
    return {side: p() for side, p in pending.items()}


def release_freed_memory() -> None:
    """Give the heap's freed pages back to the system. glibc keeps them resident: after a side's bundle
    adjustment (a window's graph, ~1 GB on a row's turn) they stayed under the fusion that followed and the
    two peaks added up (30-tree row, measured)."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to do
        pass


# A trunk detector: (colour (H, W, 3) uint8, stamp s) -> its detections, or None when it could not answer
# (a detector node that is down): the keyframe is then not cleaned and the trunks near it are flagged.
Detect = Callable[[np.ndarray, float], "list | None"]
DETECTOR_UNAVAILABLE = "detector_unavailable_nearby"  # a trunk flag


def flag_trunks_near(trunks: list[TrunkLandmark], centres: np.ndarray, radius_m: float) -> None:
    """Flag the trunks whose base is within radius_m of any of these camera centres (C, 3) m, odom: keyframes
    the detector did not see, so the trunk may have fewer views than it should (and a tree seen only from
    them is missing)."""
    for lm in trunks:
        if len(centres) and np.min(np.linalg.norm(centres - lm.base, axis=1)) <= radius_m:
            if DETECTOR_UNAVAILABLE not in lm.flags:
                lm.flags.append(DETECTOR_UNAVAILABLE)


def trunk_detector(cfg: OrchardConfig, side: str):
    """The configured source of trunk masks for one side: `detect(color, stamp) -> list[Detection]`."""
    tp = cfg.trunks
    if tp.source == "masks":
        from orchard_mapping.io.masks import MaskFolderDetector

        masks = MaskFolderDetector(tp.masks_dir, side)
        return lambda color, stamp: masks.detect_at(stamp)
    from orchard_mapping.core.detection import OnnxTrunkDetector

    model = OnnxTrunkDetector.from_params(tp)
    return lambda color, stamp: model.detect(color)


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


@dataclass(frozen=True)
class PostView:
    """One post detection of keyframe k, as its fit (core.posts.fit_post_view) reads it."""

    keyframe: int
    up_cam: np.ndarray  # (3,) the side's up in this camera
    depth: ImagePatch  # raw depth m, around the mask
    mask: ImagePatch  # bool


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
    if sum(len(v.detections) for v in views.views) < n_trunk:
        log.info("%d trunk detections lie on columns shaped as posts (straight, untapered, bare): not trunks",
                 n_trunk - sum(len(v.detections) for v in views.views))
    todo = columns_to_model(candidates, detection_places(views.views, intr), tp.min_observations,
                            tp.associate_radius_m, only=tp.geometric == "only")
    if not todo:
        return 0
    picks: dict[int, int] = {}  # frame index -> keyframe
    last = None
    for k, T in enumerate(poses):
        if last is None or np.linalg.norm(T[:3, 3] - last) >= tp.detect_every_m - 1e-6:
            picks[frame_index[k]] = k
            last = T[:3, 3]
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
                   views: TrunkViews) -> FusionResult:
    """TSDF fusion of the keyframes' depth (frame_index[k] is keyframe k's frame) with their optimised poses
    (k, 4, 4); the keyframes with a trunk detection go to `views` as fusion comes to them (cleaned as fusion moves
    on, with trunks.view_depth "cleaned")."""
    pose_of = dict(zip(frame_index, poses, strict=True))

    def frames() -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        for i, depth, color in images.frames(sorted(pose_of)):
            yield depth, color, pose_of[i]

    return fuse_side(frames(), intr, keyframes=None, on_cleaned=views, select=views.select, **asdict(cfg.fusion))


def write_cloud(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """PLY (binary), written atomically."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pc.colors = o3d.utility.Vector3dVector(colors.astype(np.float64) / 255.0)
    _write_ply_atomically(path, lambda tmp: o3d.io.write_point_cloud(tmp, pc, write_ascii=False))


def _write_ply_atomically(path: Path, write: Callable[[str], bool]) -> None:
    """write(tmp) -> success into a temporary file beside `path`, then renamed onto it."""
    tmp = path.with_name(f".{path.stem}.partial.ply")
    if not write(str(tmp)):
        tmp.unlink(missing_ok=True)
        raise OSError(f"could not write point cloud {path}")
    os.replace(tmp, path)


def write_labelled_cloud(path: Path, points: np.ndarray, colors: np.ndarray, side: np.ndarray) -> None:
    """PLY (binary) with colour and a per-point `side` label (uchar: 0 front, 1 back), written atomically."""
    import open3d as o3d

    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(np.ascontiguousarray(points, np.float32))
    pc.point.colors = o3d.core.Tensor(np.ascontiguousarray(colors, np.uint8))
    pc.point.side = o3d.core.Tensor(np.ascontiguousarray(side, np.uint8).reshape(-1, 1))
    _write_ply_atomically(path, lambda tmp: o3d.t.io.write_point_cloud(tmp, pc, write_ascii=False))


def _trajectory(stamps: np.ndarray, poses: np.ndarray, frame_id: str) -> StampedTrajectory:
    q = np.array([matrix_to_quat(T[:3, :3]) for T in poses])
    return StampedTrajectory(stamps, poses[:, :3, 3], q, frame_id)


def write_side(out: Path, sm: SideMap) -> None:
    write_tum(out / f"trajectory_{sm.side}.tum", _trajectory(sm.keyframe_stamps, sm.keyframe_poses, sm.frame_id))
    # The front end's keyframe poses before loop closure and BA: what the back end improved on.
    write_tum(out / f"odometry_{sm.side}.tum", _trajectory(sm.keyframe_stamps, sm.odometry_poses, sm.frame_id))
    if len(sm.cloud_points):
        write_cloud(out / f"{sm.side}.ply", sm.cloud_points, sm.cloud_colors)


def write_landmarks(out: Path, sides: dict[str, SideMap], cfg: OrchardConfig) -> None:
    """trunks.json and grounds.json of every side (docs/results.md)."""
    by_side = {s: (sm.frame_id, sm.trunks) for s, sm in sides.items()}
    write_trunks(out / TRUNKS_JSON, by_side, cfg.trunks.diameter_height_m)
    write_grounds(out / GROUNDS_JSON, by_side)


@dataclass(frozen=True)
class MergeOutcome:
    method: str  # merge.method that made it
    T_front_back: np.ndarray  # (4, 4) rigid odom_front <- odom_back
    pairs: tuple[tuple[int, int], ...]  # (front trunk id, back trunk id)
    alignment: SideAlignment | None  # None for the ICP baseline
    initial: InitialTransform | None
    sba: SemanticBAResult | None  # only with merge.method "semantic_ba"
    shapes: tuple[SideShapes, SideShapes] | None  # what the semantic BA measured of each side
    seconds: dict[str, float]  # per step: alignment, initial_transform, semantic_ba (or icp)


# MergeOutcome.method of a merge made without enough trunk pairs (alignment.fallback): the front views and each
# side's trunk line alone; every tree of it carries the flag MERGED_BY_GLOBAL_FEATURES
GLOBAL_FEATURES = "global_features"
MERGED_BY_GLOBAL_FEATURES = "merged_by_global_features"


def _ground_kind(lm: TrunkLandmark) -> int:
    """What a trunk's foot stands on: 2 its local ground, 1 the wider ground (no local one), 0 neither
    (its lowest visible point)."""
    return 2 if lm.ground is not None else 1 if "diameter_height_from_wide_ground" in lm.flags else 0


def _merge_axis(lm: TrunkLandmark) -> np.ndarray:
    """The trunk axis the merge uses: with the taper modelled when it was fitted (TrunkLandmark.merge_axis)."""
    return lm.merge_axis if lm.merge_axis is not None else lm.axis


def _row_direction(bases: np.ndarray) -> np.ndarray:
    """(3,) unit: the row's direction through trunk bases (T, 3) (their first principal axis), T >= 2."""
    return np.linalg.svd(bases - bases.mean(axis=0), full_matrices=False)[2][0]


def _trunk_shapes(sm: SideMap, ids: list[int], T_map_odom: np.ndarray, height_m: float, row_map: np.ndarray
                  ) -> list[TrunkShape]:
    """Each paired trunk of a side as the semantic BA measures it: its frame (origin on the whole-trunk
    axis at the diameter height, z along it, x along the row: row_map (3,) in map) and local ground, in the camera of the
    observation that saw most of it. (The band cylinder's own axis, fitted on 16 cm of trunk, tilts
    5-18 deg off the whole trunk's on the 10-tree rows: only its radius is used.)"""
    by_id = {t.id: t for t in sm.trunks}
    out = []
    for tree, lid in enumerate(ids):
        lm = by_id[lid]
        k = max(lm.observations, key=lambda o: o.band_pixels + int(o.detection.mask.sum())).keyframe
        axis_map = T_map_odom[:3, :3] @ _merge_axis(lm)
        origin_map = T_map_odom[:3, :3] @ (lm.base + height_m * _merge_axis(lm)) + T_map_odom[:3, 3]
        T_map_cam = T_map_odom @ sm.keyframe_poses[k]
        ground = None
        if lm.ground is not None:
            R, t = sm.keyframe_poses[k][:3, :3], sm.keyframe_poses[k][:3, 3]
            n = np.asarray(lm.ground.normal, float)
            ground = np.array([*(R.T @ n), n @ t + lm.ground.offset])
        out.append(TrunkShape(tree, k, np.linalg.inv(T_map_cam) @ trunk_frame(origin_map, axis_map, row_map), ground,
                              grounded=_ground_kind(lm) > 0))
    return out


def merge_sides(front: SideMap, back: SideMap, cfg: OrchardConfig) -> MergeOutcome:
    """Initial alignment (global features), the initial transform (paired trunks and grounds), then the
    semantic bundle adjustment of both sides (merge.method)."""
    def side_input(sm: SideMap) -> AlignmentSide:
        t = sm.trunks
        return AlignmentSide(sm.cloud_points, sm.keyframe_poses, np.array([x.base for x in t]).reshape(-1, 3),
                             np.array([_merge_axis(x) for x in t]).reshape(-1, 3), np.array([x.id for x in t], int),
                             sm.scale_free, np.array([np.nan if x.diameter_m is None else x.diameter_m for x in t]))

    if np.array_equal(front.keyframe_stamps, back.keyframe_stamps):
        raise AlignmentError("the two sides are one recording (the same keyframe stamps): a merge needs one "
                             "recording of each side of the row")
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    fa, ba = side_input(front), side_input(back)
    if cfg.merge.method == "icp":
        T = icp_merge(fa, ba, cfg.alignment, rng)
        pairs_icp = pair_trunks(fa, ba, T, cfg.alignment.pair_radius_m)
        return MergeOutcome("icp", T, pairs_icp, None, None, None, None, {"icp": time.perf_counter() - t0})
    al = align_sides(fa, ba, cfg.alignment, rng)
    seconds = {"alignment": time.perf_counter() - t0}
    # Too few trunks seen from both sides: the global features alone (flagged). When the fallback was taken because
    # the candidate pairs disagreed and its own alignment pairs min_pairs trunks, those pairs go on to the initial
    # transform and the semantic BA as usual (the steady scanned-tree row: 5.3 deg / 106 mm -> 1.0 deg / 38 mm).
    if al.method == "trunk_lines" and len(al.pairs) < max(2, cfg.alignment.min_pairs):
        return MergeOutcome(GLOBAL_FEATURES, al.T_front_back, al.pairs, al, None, None, None, seconds)
    by_f = {t.id: t for t in front.trunks}
    by_b = {t.id: t for t in back.trunks}
    pairs = []
    for i, j in al.pairs:
        f, b = by_f[i], by_b[j]
        both = f.ground is not None and b.ground is not None
        pairs.append(SemanticPair(i, j, _merge_axis(f), f.base, _merge_axis(b), b.base,
                                  (f.ground.normal, f.ground.point) if both else None,
                                  (b.ground.normal, b.ground.point) if both else None,
                                  (f.ground.support_offset_m, b.ground.support_offset_m) if both else (0.0, 0.0)))
    prior = None
    if cfg.merge.sigma_alignment_height_m > 0:
        c_b = np.mean([p.origin_b for p in pairs], axis=0)  # (3,) the paired back trunks' centre
        prior = HeightPrior(al.front.T_canon_odom[1, :3], c_b, al.T_front_back[:3, :3] @ c_b + al.T_front_back[:3, 3])
    t0 = time.perf_counter()
    it = initial_transform(pairs, cfg.merge, prior)
    seconds["initial_transform"] = time.perf_counter() - t0
    sba = shapes = None
    if cfg.merge.method == "semantic_ba":
        t0 = time.perf_counter()
        h = cfg.trunks.diameter_height_m
        back_poses = it.T_front_back[None] @ back.keyframe_poses
        posts = post_shapes([(front.posts, front.keyframe_poses), (back.posts, back_poses)])
        row = _row_direction(np.array([by_f[i].base for i, _ in al.pairs]))  # map = odom_front
        shapes = (SideShapes(front.keyframe_poses, _trunk_shapes(front, [i for i, _ in al.pairs], np.eye(4), h, row),
                             posts[0]),
                  SideShapes(back_poses, _trunk_shapes(back, [j for _, j in al.pairs], it.T_front_back, h, row),
                             posts[1]))
        anchor = None
        if prior is not None and cfg.semantic_ba.height_sigma_m > 0:  # the initial transform's height prior
            point = it.T_front_back[:3, :3] @ prior.point_b + it.T_front_back[:3, 3]
            anchor = HeightAnchor(prior.up, point, float(prior.up @ prior.target_f), cfg.semantic_ba.height_sigma_m)
        sba = semantic_bundle_adjust(*shapes, cfg.semantic_ba, anchor)
        seconds["semantic_ba"] = time.perf_counter() - t0
    return MergeOutcome(cfg.merge.method, it.T_front_back, al.pairs, al, it, sba, shapes, seconds)


def map_poses(m: MergeOutcome, sides: dict[str, SideMap]) -> dict[str, np.ndarray]:
    """side -> (K, 4, 4) T_map_cam of its keyframes after the merge (the semantic BA's when it ran)."""
    if m.sba is not None:
        return {"front": m.sba.front_poses, "back": m.sba.back_poses}
    return {"front": sides["front"].keyframe_poses, "back": m.T_front_back[None] @ sides["back"].keyframe_poses}


def clouds_in_map(m: MergeOutcome, sides: dict[str, SideMap]) -> dict[str, np.ndarray]:
    """side -> (P, 3) its fused cloud in map, carried along with its keyframes by the merge."""
    return {side: move_with_keyframes(sides[side].cloud_points, sides[side].keyframe_poses, P)
            for side, P in map_poses(m, sides).items()}


# m: the union of both sides' points near a tree is cropped to this cube (half side) before the local
# ground's disk is cut out of it (cheaper than measuring every point of the row against every axis).
_FOOT_CROP_M = 1.0


def _two_side_ground(clouds: dict[str, SlabIndex], Tt: np.ndarray, foot: np.ndarray, radius: float,
                     cfg: OrchardConfig, rng: np.random.Generator):
    """The tree's local ground fitted to both sides' points around the shared trunk (frame `map`).

    Each side sees its half of the 0.5 m disk, often only a patch of it away from the trunk, and a plane
    through a patch is an extrapolation at the trunk. Together the sides see the disk from both
    directions: the plane is pinned on both sides of the trunk (the paper's semantic BA shares one plane
    per tree for the same reason). Tt (4, 4) the shared trunk frame (z up its axis); foot (3,) the
    per-side estimate of the foot (the disk's centre); radius m the trunk's. None if no plane passes."""
    near = [c.within_cube(foot, _FOOT_CROP_M) for c in clouds.values()]
    pts = np.concatenate(near) if near else np.zeros((0, 3))
    z = Tt[:3, 2]
    o_bottom = Tt[:3, 3] + float((foot - Tt[:3, 3]) @ z) * z
    return ground_around_trunk(pts, o_bottom, Cylinder(z, Tt[:3, 3], radius), cfg.ground, rng)


@dataclass(frozen=True)
class BandPair:
    """What eq. objectCylinderFB reads of one tree's two trunk landmarks (it pickles: the trunk worker fits
    some trees' while the main process fits the others')."""

    bands: list[tuple]  # per side (band points (N, 3), normals (N, 3), band views, the side's band cylinder)
    intrinsics: CameraIntrinsics
    params: TrunkParams
    seed: tuple[int, ...]


def two_side_diameter(job: BandPair) -> float | None:
    """m: the diameter of one radius fitted to both sides' bands (eq. objectCylinderFB); None if the fit failed."""
    tp = job.params
    try:
        cyls = fit_cylinders_shared_radius(
            job.bands, job.intrinsics, np.random.default_rng(job.seed), threshold_m=tp.ransac_threshold_m,
            radius_range_m=(tp.radius_min_m, tp.radius_max_m), sigma_3d_m=tp.sigma_3d_m, sigma_px=tp.sigma_px,
            lam=tp.lam, huber_k=tp.huber_k, edge_snap_px=tp.edge_snap_px)
    except CylinderError:
        return None
    return 2.0 * cyls[0].radius


def two_side_trees(m: MergeOutcome, sides: dict[str, SideMap], cfg: OrchardConfig,
                   clouds: dict[str, np.ndarray] | None = None, worker: "TrunkWorker | None" = None
                   ) -> list[ResultTree]:
    """Every trunk of either side as a tree in map: paired ones with the two-side diameter of eq.
    objectCylinderFB (one radius from both sides' band points and views) and the foot on the local
    ground fitted to both sides' points, the others flagged one-sided. clouds: clouds_in_map(m, sides).
    worker: fits every other tree's two-side diameter meanwhile (the other core is idle in the merge)."""
    tp = cfg.trunks
    if clouds is None and m.sba is not None:
        clouds = clouds_in_map(m, sides)
    near = {side: SlabIndex(P) for side, P in clouds.items()} if clouds is not None else {}
    by = {side: {t.id: t for t in sides[side].trunks} for side in ("front", "back")}
    T_fb = m.T_front_back
    intr = sides["front"].intrinsics
    worker = worker if worker is not None and worker.spawned else None
    # each tree's draws from a generator of its own, so that it does not matter which process fits it
    band_pairs = {k: BandPair([(f.band_points, f.band_normals, f.band_views, f.band.cylinder),
                               (b.band_points, b.band_normals, b.band_views, b.band.cylinder)], intr, tp,
                              (cfg.seed, k, 1))
                  for k, (f, b) in enumerate((by["front"][i], by["back"][j]) for i, j in m.pairs)
                  if f.band is not None and b.band is not None}
    elsewhere = {k: worker.submit(two_side_diameter, job) for n, (k, job) in enumerate(band_pairs.items())
                 if n % 2} if worker is not None else {}
    if worker is not None:
        worker.start()
    trees: list[ResultTree] = []
    paired = {"front": set(), "back": set()}
    for k, (i, j) in enumerate(m.pairs):
        f, b = by["front"][i], by["back"][j]
        paired["front"].add(i)
        paired["back"].add(j)
        rng = np.random.default_rng((cfg.seed, k))
        if m.sba is not None and m.shapes is not None:
            # The shared trunk after the semantic BA, down its axis to the ground: each side's base placed
            # by that side's adjusted camera. A local ground (within 0.5 m) is the best evidence of the
            # foot, the wide ground (1 m, rougher: on slope_weeds a tree with a local ground on one side
            # and a wide one on the other came out 7 cm high from their mean) the next; a side with
            # neither has only its lowest trunk point (weeds may hide the foot: 15 cm too high on the
            # 2-tree test row). The best kind present decides; with neither, the lower base.
            Tt = m.sba.trunks_map[k]
            z = Tt[:3, 2]
            heights = []
            for shapes, poses, lm in ((m.shapes[0], m.sba.front_poses, f), (m.shapes[1], m.sba.back_poses, b)):
                sh = shapes.trunk(k)
                Ts = poses[sh.keyframe] @ sh.T_cam_trunk
                base_map = Ts[:3, 3] - tp.diameter_height_m * Ts[:3, 2]
                heights.append((_ground_kind(lm), float((base_map - Tt[:3, 3]) @ z)))
            best = max(kind for kind, _ in heights)
            chosen = [hh for kind, hh in heights if kind == best]
            pos = Tt[:3, 3] + (float(np.mean(chosen)) if best else min(chosen)) * z
            r = max([t.diameter_m for t in (f, b) if t.diameter_m is not None] or [0.1]) / 2  # m; 0.1: a typical trunk
            shared = _two_side_ground(near, Tt, pos, r, cfg, rng)
            if shared is not None:
                pos = shared.point
        else:  # the feet on the best ground either side has (as above), each side's carried into map
            feet = [(_ground_kind(f), f.base), (_ground_kind(b), T_fb[:3, :3] @ b.base + T_fb[:3, 3])]
            best = max(kind for kind, _ in feet)
            pos = np.mean([p for kind, p in feet if kind == best], axis=0)
        diameter, flags = None, []
        if k in band_pairs:
            diameter = (worker.result(elsewhere[k], two_side_diameter, band_pairs[k]) if k in elsewhere
                        else two_side_diameter(band_pairs[k]))
            if diameter is None:
                flags.append("two_side_fit_failed")
        if diameter is None:
            one = [t.diameter_m for t in (f, b) if t.diameter_m is not None]
            diameter = float(np.mean(one)) if one else None
            if not one:
                flags.append("trunk_hidden_at_diameter_height")
        trees.append(ResultTree(len(trees), tuple(float(v) for v in pos), diameter, per_side={
            "front": {"trunk_id": i, "diameter_m": f.diameter_m},
            "back": {"trunk_id": j, "diameter_m": b.diameter_m}}, flags=tuple(flags) + _carried_flags(f, b)))
    for side, T in (("front", np.eye(4)), ("back", T_fb)):
        for t in sides[side].trunks:
            if t.id in paired[side]:
                continue
            pos = T[:3, :3] @ t.base + T[:3, 3]
            trees.append(ResultTree(len(trees), tuple(float(v) for v in pos), t.diameter_m,
                                    per_side={side: {"trunk_id": t.id, "diameter_m": t.diameter_m}},
                                    flags=(f"seen_from_{side}_only",) + _carried_flags(t)))
    return trees


def _carried_flags(*trunks: TrunkLandmark) -> tuple[str, ...]:
    """The trunk flags a tree carries: the detector was down near it on some side (a tree there may be
    missing, or seen from one side only because of it)."""
    return (DETECTOR_UNAVAILABLE,) if any(DETECTOR_UNAVAILABLE in t.flags for t in trunks) else ()


def merge_to_trees(sides: dict[str, SideMap], cfg: OrchardConfig, worker: "TrunkWorker | None" = None
                   ) -> tuple[MergeOutcome, dict[str, np.ndarray], list[ResultTree]]:
    """The two sides merged (merge_sides), their clouds carried into map, and the trees: what `run` and the
    side merger node write. AlignmentError (MergeRefusedError's base) when the merge is refused. worker:
    fits half the trees' two-side diameters (two_side_trees)."""
    merged = merge_sides(sides["front"], sides["back"], cfg)
    clouds = clouds_in_map(merged, sides)
    trees = two_side_trees(merged, sides, cfg, clouds, worker)
    if merged.method == GLOBAL_FEATURES:
        log.warning("too few trunks seen from both sides for the semantic merge: the sides were merged from the "
                    "global features alone (front views, each side's trunk line; error up to a trunk's width), "
                    "every tree is flagged %s", MERGED_BY_GLOBAL_FEATURES)
        trees = [replace(t, flags=t.flags + (MERGED_BY_GLOBAL_FEATURES,)) for t in trees]
    log.info("sides merged (%s) on %d trunk pairs%s", merged.method, len(merged.pairs),
             ": " + "; ".join(merged.alignment.log) if merged.alignment is not None else "")
    return merged, clouds, trees


def write_merge(out: Path, m: MergeOutcome, sides: dict[str, SideMap],
                clouds: dict[str, np.ndarray] | None = None) -> None:
    """side_merge.json, both sides' trajectories in map (= odom_front), merged.ply and row.png."""
    al, it, sba = m.alignment, m.initial, m.sba
    extra: dict = {}
    if sba is not None:
        pair_ids = list(m.pairs)
        extra["semantic_ba"] = {
            "trunk_axis_gap_mm": {"before": {"median": float(np.median(list(sba.gaps_before_mm.values()))),
                                             "max": float(max(sba.gaps_before_mm.values()))},
                                  "after": {"median": float(np.median(list(sba.gaps_after_mm.values()))),
                                            "max": float(max(sba.gaps_after_mm.values()))},
                                  "per_pair": [{"front_id": pair_ids[k][0], "back_id": pair_ids[k][1],
                                                "before": sba.gaps_before_mm[k], "after": sba.gaps_after_mm[k]}
                                               for k in sorted(sba.gaps_after_mm)]},
            "error_initial": sba.error_initial, "error_final": sba.error_final, "iterations": sba.iterations}
    residuals: dict = {}
    if it is not None and al is not None:
        residuals = {"pairs": [asdict(r) for r in it.residuals], "huber_cost_initial": it.cost_initial,
                     "huber_cost_final": it.cost_final, "boundary_rms_m": al.boundary_rms_m}
    overlap = {"trunks_front": len(sides["front"].trunks), "trunks_back": len(sides["back"].trunks),
               "pairs": len(m.pairs)}
    if al is not None:  # "trunk_pairs", or "trunk_lines" where the alignment fell back (alignment.fallback)
        extra["alignment_method"] = al.method
    if al is not None:
        overlap["x_range_m"] = list(al.overlap_m)
    write_side_merge(out / SIDE_MERGE_JSON, m.T_front_back, method=m.method, residuals=residuals,
                     overlap=overlap, alignment_log=al.log if al is not None else [], seconds=m.seconds, **extra)
    poses = map_poses(m, sides)
    for side, P in poses.items():  # (K, 4, 4) T_map_cam
        write_tum(out / map_trajectory_filename(side), StampedTrajectory(
            sides[side].keyframe_stamps, P[:, :3, 3], np.array([matrix_to_quat(R) for R in P[:, :3, :3]])))
    # merged.ply: each side's cloud carried along with its keyframes into map
    own = {"front": sides["front"].keyframe_poses, "back": sides["back"].keyframe_poses}
    moved = clouds if clouds is not None else clouds_in_map(m, sides)
    write_labelled_cloud(out / MERGED_PLY, np.concatenate([moved["front"], moved["back"]]),
                         np.concatenate([sides["front"].cloud_colors, sides["back"].cloud_colors]),
                         np.repeat([0, 1], [len(moved["front"]), len(moved["back"])]))
    if al is not None:  # row.png, in the front side's canonical frame of the initial alignment
        Ta = al.T_front_back
        bases = {side: np.array([t.base for t in sides[side].trunks]).reshape(-1, 3) for side in poses}
        before = RowView("before: initial alignment", {
            "front": sides["front"].cloud_points,
            "back": sides["back"].cloud_points @ Ta[:3, :3].T + Ta[:3, 3]},
            {"front": bases["front"], "back": bases["back"] @ Ta[:3, :3].T + Ta[:3, 3]})
        label = {"semantic_ba": "semantic BA", "initial": "initial transform"}.get(m.method, m.method)
        after = RowView(f"after: {label}", moved, {
            side: move_with_keyframes(bases[side], own[side], poses[side]) for side in poses})
        write_row_png(out / ROW_PNG, al.front.T_canon_odom, [before, after], seed=0)


def run(front: str | Path, back: str | Path | None, out: str | Path, cfg: OrchardConfig,
        progress: Progress | None = None, trunk_worker: bool = False) -> RunResult:
    """Reconstruct each side and write the result folder.

    trunk_worker: model the first side's trunks, the last side's posts and half the merge's two-side fits in
    a spawned worker process (TrunkWorker; same results). `orchard-map run` does. A spawned process imports the
    caller's main module again: a script that calls this with trunk_worker=True needs the
    `if __name__ == "__main__":` guard that Python's multiprocessing asks for.

    Everything is written into a staging folder first and moved into `out` only when the whole run
    succeeded: a failed run leaves no half-written result (earlier results in `out` stay as they were).
    """
    out = Path(out)
    created = [d for d in (out, *out.parents) if not d.exists()]  # folders this run makes (deepest first)
    out.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    try:
        result = _run(Path(front), Path(back) if back is not None else None, stage, cfg, progress, trunk_worker)
        for f in sorted(stage.iterdir()):
            os.replace(f, out / f.name)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        for d in created:  # a failed run leaves no folder it created itself (rmdir: only if still empty)
            try:
                d.rmdir()
            except OSError:
                break
        raise
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    if result.merge_refused is not None:
        # The sides' own results are complete and stay; the merge is not guessed (exit code 2), and
        # an earlier run's merge outputs in `out` would now contradict them.
        for name in MERGE_OUTPUTS:
            for f in out.glob(name):
                f.unlink()
        raise MergeRefusedError(
            f"the two sides were not merged: {result.merge_refused}. Each side's results (trajectories, "
            f"clouds, trunks.json) are in {out}; no side_merge.json and no trees in map were written. "
            "Run with --set merge.method=off to reconstruct the sides without trying to merge them.")
    return RunResult(out, result.sides, result.timings, result.merge_refused)


def _run(front: Path, back: Path | None, out: Path, cfg: OrchardConfig, progress: Progress | None,
         trunk_worker: bool) -> RunResult:
    timings = Timings()
    t0 = t_start = time.perf_counter()
    seqs = open_sides(front, back, cfg)
    timings.add("read_bags", time.perf_counter() - t0)
    labelled = back is None
    sides: dict[str, SideMap] = {}
    refused: str | None = None
    # Two sides with trunks: the first side's trunks are modelled in a worker process while the next is finished
    worker = (TrunkWorker() if trunk_worker and cfg.trunks.source != "off" and cfg.input.mode == "rgbd"
              and (DRIVE in seqs or len(seqs) > 1) else None)
    try:
        if DRIVE in seqs:
            seq = seqs.pop(DRIVE)
            timings.frames += len(seq)
            timings.recording_duration_s += seq.duration
            for side, sm in reconstruct_drive(seq, cfg, timings, progress, worker).items():
                sides[side] = sm
                write_side(out, sm)
        pending: dict[str, PendingSide] = {}
        for i, (side, seq) in enumerate(seqs.items()):
            timings.frames += int(np.sum(_side_mask(seq, side))) if labelled else len(seq)
            if labelled:
                st = seq.stamps[_side_mask(seq, side)]
                timings.recording_duration_s += float(st[-1] - st[0]) if len(st) > 1 else 0.0
            else:
                timings.recording_duration_s += seq.duration
            pending[side] = reconstruct_side_later(seq, side, cfg, timings, labelled, progress, worker,
                                                   here=i == len(seqs) - 1)
        for side, p in pending.items():
            sides[side] = p()
            write_side(out, sides[side])
        if cfg.trunks.source != "off" and cfg.input.mode == "rgbd":
            write_landmarks(out, sides, cfg)
            if cfg.merge.method != "off" and set(sides) == {"front", "back"}:
                t0 = time.perf_counter()
                try:
                    merged, clouds, trees = merge_to_trees(sides, cfg, worker)
                except AlignmentError as err:
                    log.warning("side merge refused: %s (no side_merge.json written)", err)
                    refused = str(err)
                else:
                    write_merge(out, merged, sides, clouds)
                    write_trees(out, trees, frame="map")
                timings.add("merge", time.perf_counter() - t0)
    finally:
        if worker is not None:
            worker.close()
    timings.wall_s = time.perf_counter() - t_start
    write_timings(out / "timings.json", timings.stages, frames=timings.frames,
                  recording_duration_s=timings.recording_duration_s, wall_s=timings.wall_s)
    atomic_write_text(out / "config.effective.yaml", dump_yaml(cfg))
    return RunResult(out, sides, timings, refused)
