"""One side of the row: the front end fed a frame at a time (`SideSession`), then loop detection, pose graph,
bundle adjustment, TSDF fusion and the side's trunks (`finish_side_geometry`, `finish_side`); one side of a bag
(`reconstruct_side`) or both sides of one drive round the row (`reconstruct_drive`), or of every row of a drive
along a block (`drive_rows`)."""

from __future__ import annotations

import ctypes
import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from orchard_mapping.config import OrchardConfig
from orchard_mapping.core.bundle_adjustment import BAResult, bundle_adjust_windowed, optimise_pose_graph
from orchard_mapping.core.fruit import SideFruit
from orchard_mapping.core.odometry import RGBDFrontEnd
from orchard_mapping.core.sidemap import FrontEndResult, LoopClosure, SideGeometry, SideMap
from orchard_mapping.core.sides import SideSplitter
from orchard_mapping.core.trunks import TrunkGround
from orchard_mapping.core.types import CameraIntrinsics, RGBDFrame
from orchard_mapping.errors import BagFormatError
from orchard_mapping.io.bags import RGBDSequence
from orchard_mapping.io.block import DrivePass
from orchard_mapping.pipeline.fruit import FruitTap
from orchard_mapping.pipeline.sides import BagKeyframeImages, KeyframeImages, Progress, Timings, frames_of, side_mask
from orchard_mapping.pipeline.trunks import Detect, TrunkJob, TrunkWorker, fit_posts, model_trunks, with_trunks
from orchard_mapping.pipeline.views import EarlyDetections, TrunkViews, add_column_views, fuse_keyframes

log = logging.getLogger(__name__)


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
    fruit: SideFruit | None = None
    if cfg.input.mode == "rgbd":
        t0 = time.perf_counter()
        frame_index = [k.frame_index for k in fe.keyframes]
        views = TrunkViews(cfg, stamps, ba.poses, intr, job.detections, frame_index)
        tap = FruitTap(side, stamps, ba.poses, intr, cfg.fruit) if cfg.fruit.enabled else None
        fused = fuse_keyframes(job.images, frame_index, ba.poses, intr, cfg, views, tap)
        points, colors = fused.points, fused.colors
        if tap is not None:
            t1 = time.perf_counter()
            fruit = tap.side_fruit()
            timings.add(f"fruit_{side}", tap.seconds + time.perf_counter() - t1)
            log.info("%s: %d fruit from %d views in %d keyframes", side, len(fruit.positions),
                     len(tap.observations), len(tap.picks))
        timings.add(f"fusion_{side}", time.perf_counter() - t0 - (tap.seconds if tap is not None else 0.0))
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
        fruit=fruit,
    )
    return side_map, trunk_job


# The grounds of a side's trunk landmarks fitted elsewhere (the live graph's local_ground_fitter node) from the
# side's geometry: core.trunks.TrunkGround per landmark, or None to fit them here
GroundsElsewhere = Callable[[SideGeometry], "list[TrunkGround] | None"]


def finish_side(job: SideHandover, timings: Timings, grounds_elsewhere: GroundsElsewhere | None = None) -> SideMap:
    """Loop detection, pose graph, bundle adjustment, TSDF fusion (cleaning the keyframes with a trunk
    detection, with trunks.view_depth "cleaned"), trunk cylinders and local grounds: the side map.
    grounds_elsewhere: asked for the trunks' grounds once the side is fused; the trunk cylinders are then
    fitted against its answer (the same `model_trunks`, whose first step it stands for)."""
    if grounds_elsewhere is None:
        return finish_side_later(job, timings, None)()
    side_map, trunk_job = finish_side_geometry(job, timings)
    if trunk_job is None:
        return side_map
    grounds = grounds_elsewhere(trunk_job.geometry()) if job.cfg.trunks.source != "off" else None
    return with_trunks(side_map, model_trunks(trunk_job, grounds=grounds), timings)


PendingSide = Callable[[], SideMap]


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


def reconstruct_side(seq: RGBDSequence, side: str, cfg: OrchardConfig, timings: Timings, labelled: bool = False,
                     progress: Progress | None = None) -> SideMap:
    """One side of a bag through a `SideSession` (fusion reads the keyframes' images from the bag again)."""
    return reconstruct_side_later(seq, side, cfg, timings, labelled, progress, None)()


def reconstruct_side_later(seq: RGBDSequence, side: str, cfg: OrchardConfig, timings: Timings, labelled: bool,
                           progress: Progress | None, worker: "TrunkWorker | None", here: bool = False) -> "PendingSide":
    """`reconstruct_side` with the side's trunk modelling handed to `worker` (None, or here=True: done here;
    `worker` still starts an earlier side's job once this side's front end is over)."""
    n = int(np.sum(side_mask(seq, side))) if labelled else len(seq)
    session = SideSession(side, seq.intrinsics, cfg, BagKeyframeImages(seq, side, labelled), bag=seq.bag)
    t0 = time.perf_counter()
    for i, frame in enumerate(frames_of(seq, side, labelled)):
        session.add(frame)
        if progress:
            progress(side, i + 1, n)
    session.seconds = time.perf_counter() - t0  # the front end's stage includes decoding the bag's images
    return session.finish_later(timings, worker, here)


@dataclass(frozen=True)
class DriveRow:
    """A row of a drive, its sides reconstructed: what the drive gave of it once it turned into the next row or
    ended. sides holds the sides it went along (one where it went along one side only)."""

    row: int
    sides: dict[str, SideMap]
    passes: tuple[DrivePass, ...]
    timings: Timings  # this row's stages, frames and duration
    last: bool  # the drive ended on this row


def drive_rows(seq: RGBDSequence, cfg: OrchardConfig, progress: Progress | None = None,
               worker: "TrunkWorker | None" = None) -> Iterator[DriveRow]:
    """One continuous drive without side labels, row by row: each frame tracked by its pass's `SideSession`, a
    pass ending half way round each turn, where core.sides.SideSplitter (the rule the live odometry node follows)
    says; the turns also tell the row (into the next row, or round the row end to its other side). A row is
    finished (back end, fusion, trunks) and yielded as soon as the drive turns into the next row, before that
    row is tracked: one row's sides are in memory at a time."""
    turns = SideSplitter(cfg.input.side_source)
    row = 1
    sessions: dict[str, SideSession] = {}
    passes: list[DrivePass] = []
    seconds: dict[str, float] = {}
    session: SideSession | None = None
    first = 0
    t0 = time.perf_counter()
    for i, frame in enumerate(seq):
        if session is None:
            if turns.row() != row:
                yield _finish_row(row, sessions, seconds, passes, worker, last=False)
                row, sessions, passes, seconds = turns.row(), {}, [], {}
            side = turns.side()
            if side in sessions:
                raise BagFormatError(
                    f"the drive turns back to the {side} side of row {row} at frame {i} ({frame.stamp:.3f} s): a drive "
                    "goes along each side of a row once (front, U-turn round the row end, back; then, along a block, "
                    "a turn into the next row)", bag=seq.bag)
            session = sessions[side] = SideSession(side, seq.intrinsics, cfg, BagKeyframeImages(seq, side, False),
                                                   bag=seq.bag)
            first, first_stamp, t0 = i, frame.stamp, time.perf_counter()
        pose, _ = session.add(frame)
        if turns.after_pose(pose):
            seconds[session.side] = time.perf_counter() - t0  # the front end's stage includes decoding the bag's images
            passes.append(DrivePass(session.side, first, i, first_stamp, frame.stamp))
            session = None
        if progress:
            progress("drive", i + 1, len(seq))
        last_i, last_stamp = i, frame.stamp
    if session is not None:
        seconds[session.side] = time.perf_counter() - t0
        passes.append(DrivePass(session.side, first, last_i, first_stamp, last_stamp))
    if sessions:
        yield _finish_row(row, sessions, seconds, passes, worker, last=True)


def _finish_row(row: int, sessions: dict[str, SideSession], seconds: dict[str, float], passes: list[DrivePass],
                worker: "TrunkWorker | None", last: bool) -> DriveRow:
    """The row's sides finished: a side's trunks are modelled in the worker while the next side is finished."""
    log.info("drive, row %d: %s", row, ", ".join(f"{p.side} {p.frames} frames" for p in passes))
    timings = Timings()
    timings.frames = sum(p.frames for p in passes)
    timings.recording_duration_s = passes[-1].last_stamp - passes[0].first_stamp
    pending = {}
    names = list(sessions)
    for side, s in sessions.items():
        s.seconds = seconds[side]
        pending[side] = s.finish_later(timings, worker, here=side == names[-1])
    return DriveRow(row, {side: p() for side, p in pending.items()}, tuple(passes), timings, last)


def reconstruct_drive(seq: RGBDSequence, cfg: OrchardConfig, timings: Timings,
                      progress: Progress | None = None, worker: "TrunkWorker | None" = None) -> dict[str, SideMap]:
    """One continuous drive round one row without side labels (`drive_rows` of a drive of one row): its sides.
    BagFormatError where the drive goes on to a second row (pipeline.block reads such a drive)."""
    rows = drive_rows(seq, cfg, progress, worker)
    row = next(rows, None)
    if row is None:
        raise BagFormatError("the drive holds no frame", bag=seq.bag)
    if not row.last:
        rows.close()
        raise BagFormatError(f"the drive goes on to a second row after {row.passes[-1].last_stamp:.3f} s (a turn into "
                             "the next row): a block, one result per row (`orchard-map run` reads it so)", bag=seq.bag)
    for stage, sec in row.timings.stages.items():
        timings.add(stage, sec)
    return row.sides


def release_freed_memory() -> None:
    """Give the heap's freed pages back to the system. glibc keeps them resident: after a side's bundle
    adjustment (a window's graph, ~1 GB on a row's turn) they stayed under the fusion that followed and the
    two peaks added up (30-tree row, measured)."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc: nothing to do
        pass
