"""Baseline: dense frame-to-frame RGB-D odometry with Open3D (for benchmarks/single_side.py).

Each frame is aligned to the previous one with Open3D's tensor multi-scale RGB-D odometry
(`o3d.t.pipelines.odometry.rgbd_odometry_multi_scale`, on the CPU) and the relative motions are
chained from the identity: poses are T_odom_cam of the colour optical frame (x right, y down,
z forward) with odom = the first frame's camera. No keyframes, no map, no loop closure: the
plain dense odometry the feature front end (core/odometry.py) is compared with.

Settings (defaults of `dense_rgbd_odometry`), tuned on the simulator's camera (640x480 at 15 Hz,
depth sd ~ 0.004 z^2: 6 mm at the trunks 1.25 m away, 3.6 cm at 3 m, 6.4 cm at 4 m; colour gain
jitter 4 %) over whole sides of a 2-tree standard row (247 frames each: level sweep 1.25 m from
the trunks, then the raised sweep 3 m up, tilted 35 deg down, most depth 2-4.5 m away). Numbers:
drift % / ATE % of the path, front / back side, and the median per-pair error.

- depth is float32 metres: depth_scale 1.0 (Open3D's default 1000 is for 16-bit millimetres).
  Missing depth (0) is invalid to Open3D (ClipTransform maps values <= 0 to NaN).
- method "point_to_plane" (default): ICP on the depth vertex/normal maps, the fastest. It slides:
  trunks, ground and leaves are mostly surfaces parallel to the motion along the row, which only
  their edges constrain (it under-estimated the step along the row by 5-10 % on the level sweep). Its defaults are
  depth_max_m 5.0, depth_diff_m 0.07, depth Huber delta 0.05 (Open3D's): 4.4 / 1.0 and
  5.4 / 1.5 %, 2 mm per pair. With 3 m / 0.03 m (good on the level sweep alone, 1.3 mm per pair) the
  raised sweep has too little depth within range: 15 % of the pairs failed, 18 / 50 % drift; with
  4 m / 0.05 m 16 / 17 %; 6 m / 0.10 m was no better than 5 m (4.7 / 4.3 %).
- "hybrid" adds the photometric term (Open3D's Hybrid), "intensity" uses it alone. Their defaults:
  depth_max_m 4.0, depth_diff_m 0.05, Huber 0.03: hybrid 0.19 / 0.07 and 0.34 / 0.14 %, 0.5-0.7 mm
  per pair; at 5 m / 0.07 m 0.9 / 1.1 % drift, at 3 m / 0.03 m 4.4 / 12.7 %. Started from the
  constant-velocity guess, hybrid diverged on the first pairs of a sequence (40-100 mm, fitness
  falling below 0.1): the photometric basin is narrower than a 4 cm step. So by default
  (`photometric_init="point_to_plane"`) each pair runs point-to-plane first (same settings) and
  the photometric method from its result, at about twice the time per pair. Exposure changes did
  not cause the failures; normalising each frame's brightness made hybrid worse, so colour is only
  scaled to [0, 1] (the intensity Huber delta 0.1 is in those units).
- depth_diff_m is Open3D's `depth_outlier_trunc`, the largest point-to-point distance of a
  correspondence, and must exceed the depth Huber delta (Open3D warns otherwise); it has to grow
  with depth_max_m, as the noise does.
- iterations per pyramid level, coarsest first (3 levels: 1/4, 1/2, full resolution): Open3D's
  default (10, 5, 3); (6, 3, 2), (20, 10, 5) and a 4th level gave the same error within 0.1 mm.
- initial guess: the previous pair's motion (constant velocity); `constant_velocity=False` starts
  from the identity (same error on the level sweep; more failed pairs on the raised sweep).
- a pair that Open3D cannot solve (it raises on a singular system: too few correspondences), whose
  result is non-finite, or whose fitness (Open3D's fraction of pixels with a valid correspondence:
  0.2-0.3 on the level sweep) is below `min_fitness` is replaced by the guess and counted in
  `DenseOdometryResult.failed_pairs`; so is a pair moving faster than a hand-held camera can
  (max_speed_mps 3 m/s, max_turn_dps 180 deg/s, from the stamps): a diverged pair accepted once
  would otherwise seed the next pair's constant-velocity guess and diverge the rest.
Speed: point-to-plane 120-240 ms per pair, hybrid 270-450 ms here on 2 busy shared cores
(docs/dependencies.md: point-to-plane 47-71 ms on an idle machine).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import open3d as o3d
import open3d.core as o3c

from orchard_mapping.core.types import CameraIntrinsics, RGBDFrame
from orchard_mapping.errors import OrchardMappingError

__all__ = ["DEFAULT_DEPTH_SETTINGS", "DenseOdometryError", "DenseOdometryResult", "dense_rgbd_odometry", "dense_rgbd_odometry_result"]

Method = Literal["point_to_plane", "hybrid", "intensity"]

_METHODS = {
    "point_to_plane": o3d.t.pipelines.odometry.Method.PointToPlane,
    "hybrid": o3d.t.pipelines.odometry.Method.Hybrid,
    "intensity": o3d.t.pipelines.odometry.Method.Intensity,
}
_CPU = o3c.Device("CPU:0")
# Per method: (depth_max_m, depth_diff_m, depth_huber_delta_m); see the module notes.
DEFAULT_DEPTH_SETTINGS: dict[str, tuple[float, float, float]] = {
    "point_to_plane": (5.0, 0.07, 0.05),
    "hybrid": (4.0, 0.05, 0.03),
    "intensity": (4.0, 0.05, 0.03),
}


class DenseOdometryError(OrchardMappingError):
    """Input unusable for the dense baseline: no depth, wrong shape/dtype, changing intrinsics, bad settings."""


@dataclass
class DenseOdometryResult:
    stamps: np.ndarray  # (N,) s
    poses: np.ndarray  # (N, 4, 4) T_odom_cam, odom = first camera
    pair_seconds: np.ndarray  # (N-1,) s, Open3D call per consecutive pair
    fitness: np.ndarray  # (N-1,) inlier fraction per pair (Open3D's fitness)
    failed_pairs: list[int] = field(default_factory=list)  # index k of pairs (k-1, k) replaced by the guess


def _check_frame(frame: RGBDFrame, intr: CameraIntrinsics | None, k: int) -> None:
    if frame.depth is None:
        raise DenseOdometryError(f"frame {k} (stamp {frame.stamp}): no depth; the dense baseline needs RGB-D")
    d, c = np.asarray(frame.depth), np.asarray(frame.color)
    if d.ndim != 2 or d.dtype != np.float32:
        raise DenseOdometryError(f"frame {k}: depth must be (H, W) float32 metres, got {d.shape} {d.dtype}")
    if c.ndim != 3 or c.shape[2] != 3 or c.dtype != np.uint8:
        raise DenseOdometryError(f"frame {k}: colour must be (H, W, 3) uint8 RGB, got {c.shape} {c.dtype}")
    if c.shape[:2] != d.shape:
        raise DenseOdometryError(f"frame {k}: colour {c.shape[:2]} and depth {d.shape} differ in size")
    fi = frame.intrinsics
    if (fi.height, fi.width) != d.shape:
        raise DenseOdometryError(f"frame {k}: image {d.shape} does not match intrinsics {fi.width}x{fi.height}")
    if intr is not None and (fi.width, fi.height, fi.fx, fi.fy, fi.cx, fi.cy) != (
            intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy):
        raise DenseOdometryError(f"frame {k}: intrinsics changed within the sequence")


def _angle_deg(T: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))


def _rgbd(frame: RGBDFrame) -> o3d.t.geometry.RGBDImage:
    depth = np.nan_to_num(np.asarray(frame.depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    rgb = np.ascontiguousarray(frame.color, dtype=np.float32) / np.float32(255.0)  # [0, 1] for the Huber delta
    color = o3d.t.geometry.Image(o3c.Tensor(rgb, device=_CPU))
    return o3d.t.geometry.RGBDImage(color, o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth), device=_CPU)))


def dense_rgbd_odometry_result(
    frames: Iterable[RGBDFrame],
    *,
    method: Method = "point_to_plane",
    depth_max_m: float | None = None,
    depth_diff_m: float | None = None,
    depth_huber_delta_m: float | None = None,
    intensity_huber_delta: float = 0.1,
    iterations: Sequence[int] = (10, 5, 3),
    constant_velocity: bool = True,
    photometric_init: Literal["point_to_plane", "guess"] = "point_to_plane",
    min_fitness: float = 0.05,
    max_speed_mps: float = 3.0,
    max_turn_dps: float = 180.0,
) -> DenseOdometryResult:
    """Frame-to-frame dense odometry with timings and per-pair fitness (see the module notes).

    depth_max_m, depth_diff_m, depth_huber_delta_m: None = the method's DEFAULT_DEPTH_SETTINGS.
    """
    if method not in _METHODS:
        raise DenseOdometryError(f"method must be one of {sorted(_METHODS)}, got {method!r}")
    d_max, d_diff, d_huber = DEFAULT_DEPTH_SETTINGS[method]
    depth_max_m = d_max if depth_max_m is None else depth_max_m
    depth_diff_m = d_diff if depth_diff_m is None else depth_diff_m
    depth_huber_delta_m = d_huber if depth_huber_delta_m is None else depth_huber_delta_m
    if not (depth_max_m > 0 and depth_diff_m > 0 and depth_huber_delta_m > 0 and intensity_huber_delta > 0):
        raise DenseOdometryError("depth_max_m, depth_diff_m and the Huber deltas must be > 0")
    if not (max_speed_mps > 0 and max_turn_dps > 0):
        raise DenseOdometryError("max_speed_mps and max_turn_dps must be > 0")
    if len(iterations) == 0 or any(int(i) < 1 for i in iterations):
        raise DenseOdometryError(f"iterations must be >= 1 per pyramid level, got {tuple(iterations)}")
    if photometric_init not in ("point_to_plane", "guess"):
        raise DenseOdometryError(f"photometric_init must be 'point_to_plane' or 'guess', got {photometric_init!r}")
    two_stage = method != "point_to_plane" and photometric_init == "point_to_plane"
    criteria = [o3d.t.pipelines.odometry.OdometryConvergenceCriteria(int(i)) for i in iterations]
    params = o3d.t.pipelines.odometry.OdometryLossParams(depth_diff_m, depth_huber_delta_m, intensity_huber_delta)
    stamps: list[float] = []
    poses: list[np.ndarray] = []
    seconds: list[float] = []
    fitness: list[float] = []
    failed: list[int] = []
    intr: CameraIntrinsics | None = None
    K: o3c.Tensor | None = None
    prev = None
    velocity = np.eye(4)  # T_prev_cur of the last pair
    for k, frame in enumerate(frames):
        _check_frame(frame, intr, k)
        if intr is None:
            intr = frame.intrinsics
            K = o3c.Tensor(intr.K, dtype=o3c.float64)
        cur = _rgbd(frame)
        if prev is None:
            pose = np.eye(4)
        else:
            guess = velocity if constant_velocity else np.eye(4)
            t0 = time.perf_counter()
            # source = current frame, target = previous: the result maps current-camera points into the
            # previous camera, i.e. T_prev_cur.
            init = o3c.Tensor(guess, dtype=o3c.float64)
            try:
                if two_stage:
                    init = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
                        cur, prev, K, init, 1.0, float(depth_max_m), criteria, _METHODS["point_to_plane"],
                        params).transformation
                res = o3d.t.pipelines.odometry.rgbd_odometry_multi_scale(
                    cur, prev, K, init, 1.0, float(depth_max_m), criteria, _METHODS[method], params)
                T, fit = res.transformation.numpy().astype(np.float64), float(res.fitness)
            except RuntimeError:  # Open3D: "Singular 6x6 linear system detected, tracking failed."
                T, fit = np.full((4, 4), np.nan), 0.0
            seconds.append(time.perf_counter() - t0)
            fitness.append(fit)
            dt = max(float(frame.stamp) - stamps[-1], 1e-3)
            if (not np.isfinite(T).all() or fit < min_fitness or np.linalg.norm(T[:3, 3]) > max_speed_mps * dt
                    or _angle_deg(T) > max_turn_dps * dt):
                failed.append(k)
                T = guess
            velocity = T
            pose = poses[-1] @ T
        stamps.append(float(frame.stamp))
        poses.append(pose)
        prev = cur
    if not poses:
        raise DenseOdometryError("no frames")
    return DenseOdometryResult(np.array(stamps), np.array(poses), np.array(seconds), np.array(fitness), failed)


def dense_rgbd_odometry(frames: Iterable[RGBDFrame], **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (N,) s, poses (N, 4, 4) T_odom_cam) by chaining Open3D's dense RGB-D odometry frame to frame.

    Keyword arguments as `dense_rgbd_odometry_result`: method ("point_to_plane" | "hybrid" |
    "intensity"), depth_max_m, depth_diff_m (None: per method), depth_huber_delta_m, intensity_huber_delta,
    iterations (per pyramid level, coarsest first), constant_velocity, photometric_init, min_fitness,
    max_speed_mps, max_turn_dps.
    Raises DenseOdometryError on unusable input (no depth, wrong dtype/shape, no frames).
    """
    r = dense_rgbd_odometry_result(frames, **kwargs)
    return r.stamps, r.poses
