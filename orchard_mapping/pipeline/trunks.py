"""Trunk and post modelling of one side once its cloud is fused (`model_trunks`: its grounds, `fit_grounds`,
then its cylinders; `fit_posts`), the two-side
diameter of a paired tree (`two_side_diameter`), the configured trunk detector, and the worker process that runs
these jobs beside the main one (`TrunkWorker`: its jobs, `TrunkJob` and `BandPair`, pickle)."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from dataclasses import dataclass, replace

import numpy as np

from orchard_mapping.config import OrchardConfig
from orchard_mapping.core.cylinder import CylinderError, fit_cylinders_shared_radius
from orchard_mapping.core.posts import build_post_landmarks, fit_post_view, separate_trunks_from_posts
from orchard_mapping.core.sidemap import SideGeometry, SideMap
from orchard_mapping.core.trunks import (
    TrunkGround,
    TrunkLandmark,
    TrunkParams,
    TrunkView,
    fit_side_grounds,
    fit_trunk_cylinders,
)
from orchard_mapping.core.types import CameraIntrinsics, ImagePatch
from orchard_mapping.pipeline.sides import Timings

log = logging.getLogger(__name__)


# A trunk detector: (colour (H, W, 3) uint8, stamp s) -> its detections, or None when it could not answer
# (a detector node that is down): the keyframe is then not cleaned and the trunks near it are flagged.
Detect = Callable[[np.ndarray, float], "list | None"]


DETECTOR_UNAVAILABLE = "detector_unavailable_nearby"  # a trunk flag


# trunk flag: every view of it was made from the geometry of a column (trunks.geometric), none by the detector
FOUND_BY_GEOMETRY = "found_by_geometry"


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


def flag_trunks_near(trunks: list[TrunkLandmark], centres: np.ndarray, radius_m: float) -> None:
    """Flag the trunks whose base is within radius_m of any of these camera centres (C, 3) m, odom: keyframes
    the detector did not see, so the trunk may have fewer views than it should (and a tree seen only from
    them is missing)."""
    for lm in trunks:
        if len(centres) and np.min(np.linalg.norm(centres - lm.base, axis=1)) <= radius_m:
            if DETECTOR_UNAVAILABLE not in lm.flags:
                lm.flags.append(DETECTOR_UNAVAILABLE)


@dataclass(frozen=True)
class PostView:
    """One post detection of keyframe k, as its fit (core.posts.fit_post_view) reads it."""

    keyframe: int
    up_cam: np.ndarray  # (3,) the side's up in this camera
    depth: ImagePatch  # raw depth m, around the mask
    mask: ImagePatch  # bool


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

    def geometry(self) -> SideGeometry:
        """What fitting the side's grounds reads (`fit_grounds`; the live graph sends it to its ground fitter)."""
        return SideGeometry(self.side, getattr(self.cfg.frames, f"odom_{self.side}"), float(self.stamps[-1]),
                            self.intrinsics, self.poses, self.points, self.views)


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


def fit_grounds(geometry: SideGeometry, cfg: OrchardConfig) -> list[TrunkGround]:
    """The side's trunk landmarks with their coarse axes and local grounds (core.trunks.fit_side_grounds): the
    first step of `model_trunks` (on `TrunkJob.geometry()`), and what the live graph's local_ground_fitter node
    publishes."""
    return fit_side_grounds(geometry.cloud_points, geometry.keyframe_poses, geometry.views, geometry.intrinsics,
                            cfg.trunks, cfg.ground, cfg.seed)


def model_trunks(job: TrunkJob, post_model: "Callable[[], PostModel] | None" = None,
                 grounds: "list[TrunkGround] | None" = None) -> TrunkModel:
    """Post landmarks from the post views, trunk landmarks with their local grounds from the fused cloud and the
    trunk views; a trunk that is a post is set aside. Pure: the same job gives the same model in any process.
    post_model: the posts fitted elsewhere (called once the trunks are modelled), instead of here first.
    grounds: the landmarks' grounds fitted elsewhere (`fit_grounds` on this job, in the local_ground_fitter
    node), instead of here: only the trunk cylinders are fitted then."""
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
        if grounds is None:
            grounds = fit_grounds(job.geometry(), cfg)
        trunks = fit_trunk_cylinders(job.points, job.views, job.intrinsics, cfg.trunks, grounds, cfg.seed)
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
            with _sigint_held():  # the process is started by the first submit
                self._submit_waiting()
        else:
            self._submit_waiting()

    def _submit_waiting(self) -> None:
        assert self._pool is not None
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

    def close(self, abandon: bool = False) -> None:
        """Shut the process down once its job is done; abandon: at once (a stopped run: Ctrl-C should not wait
        the seconds a side's trunks take)."""
        for _, _, future in self._waiting:
            future.cancel()
        self._waiting = []
        if self._pool is not None:
            if abandon:
                # ProcessPoolExecutor has no public way to stop a busy worker before Python 3.14's
                # terminate_workers; its pool then breaks, which shutdown below handles
                stop = getattr(self._pool, "terminate_workers", None)
                if stop is not None:
                    stop()
                else:
                    for proc in list(getattr(self._pool, "_processes", {}).values()):
                        proc.terminate()
            self._pool.shutdown(wait=True, cancel_futures=True)


@contextlib.contextmanager
def _sigint_held() -> Iterator[None]:
    """SIGINT held off while this thread starts the worker process, and blocked in the worker for its life.

    Ctrl-C reaches every process of the terminal's group, and the worker, hit in its imports or in a job, printed
    a traceback of its own; the main process stops the run and shuts the worker down. The mask is inherited
    across fork and exec. Blocking it in this thread is not enough for the main process itself: the kernel then
    hands the signal to another thread (onnxruntime's), and Python raises KeyboardInterrupt here all the same,
    possibly between the worker's exec and the write of its start-up data, whereupon the worker died with
    "EOFError: Ran out of input" and its traceback (seen once in CI). So in the main thread a Ctrl-C meanwhile
    is only noted, and raised once the worker is started: held, not lost."""
    if not hasattr(signal, "pthread_sigmask"):  # not POSIX: no process group gets the signal either
        yield
        return
    import threading

    noted: list[int] = []
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, lambda signum, frame: noted.append(signum))
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
            if noted and callable(previous):  # Python's own handler raises KeyboardInterrupt here
                previous(signal.SIGINT, None)
            elif noted and previous == signal.SIG_DFL:
                os.kill(os.getpid(), signal.SIGINT)


def _pass_on(done: Future, out: Future) -> None:
    """Hand a finished future's outcome on to another future."""
    if done.cancelled():
        out.cancel()
    elif done.exception() is not None:
        out.set_exception(done.exception())
    else:
        out.set_result(done.result())
