"""Baseline: dense frame-to-frame RGB-D odometry with Open3D (for benchmarks/single_side.py).

Each frame is aligned to the previous one with Open3D's tensor multi-scale RGB-D odometry
(`o3d.t.pipelines.odometry.rgbd_odometry_multi_scale`, on the CPU) and the relative motions are
chained from the identity: poses are T_odom_cam of the colour optical frame (x right, y down,
z forward) with odom = the first frame's camera. No keyframes, no map, no loop closure: the
plain dense odometry the feature front end (core/odometry.py) is compared with.

Settings (defaults of `dense_rgbd_odometry`), tuned on 20 consecutive simulated frames (standard
scenario, 640x480 at 15 Hz, ~4 cm between frames, trunks ~1.25 m away, depth sd ~ 0.004 z^2,
exposure jitter); per-pair error against the true relative motion, median (max):
- method "point_to_plane" (default): ICP on the depth vertex/normal maps. 1.3 (2.4) mm,
  0.06 (0.10) deg per pair; on 5 other pairs of the same row 3.5 (4.6) mm, 0.13 (0.19) deg: it
  under-estimates the motion along the row by ~10 % (trunks, ground and leaves are mostly planes
  parallel to the motion, which only their edges constrain).
- "hybrid" adds the photometric term, "intensity" uses it alone. Started from the
  constant-velocity guess, hybrid reached 0.4 mm / 0.01 deg on most pairs but diverged on the first
  pairs of a sequence (40-100 mm, up to 5.8 deg, fitness falling from ~0.2 to < 0.1): the
  photometric basin is narrower than a 4 cm step. So by default (`photometric_init=
  "point_to_plane"`) each pair runs point-to-plane first and the photometric method from its
  result: 0.4 (1.0) mm, 0.012 (0.05) deg on the first 20 frames and 0.46 (0.8) mm on the other 5,
  at twice the time per pair. Exposure changes (simulated gain sd 4 %) did not cause the failures;
  normalising each frame's brightness made hybrid worse, so colour is only scaled to [0, 1].
- depth is float32 metres: depth_scale 1.0 (Open3D's default 1000 is for 16-bit millimetres).
  Missing depth (0) is invalid to Open3D (ClipTransform maps values <= 0 to NaN).
- depth_max_m 3.0: beyond 3 m the noise sd exceeds 3.6 cm and the neighbouring rows (~4.6 m) show.
  4 m was slightly better on these frames (1.1 mm), 5 m much worse (6.6 mm): the far, noisy rows
  then dominate the normals. The fusion uses the same 3 m.
- depth_diff_m 0.03 (Open3D's `depth_outlier_trunc`, largest point-to-point distance of a
  correspondence; ~5 noise sd at the trunks) with a 0.02 m depth Huber delta: Open3D's defaults
  (0.07 / 0.05) were 2.4x worse (3.1 mm, 0.16 deg per pair); 0.02 / 0.01 let single pairs fail
  (12 mm, 0.6 deg). The Huber delta must stay below depth_diff_m (Open3D warns otherwise).
- iterations per pyramid level, coarsest first (3 levels: 1/4, 1/2, full resolution): Open3D's
  default (10, 5, 3). (6, 3, 2), (20, 10, 5) and a 4th level gave the same error within 0.1 mm.
- initial guess: the previous pair's motion (constant velocity; same error here as the identity,
  safer for faster motion); `constant_velocity=False` starts from the identity.
- a pair that Open3D cannot solve (it raises on a singular system: too few correspondences), whose
  result is non-finite, or whose fitness (Open3D's fraction of pixels with a valid
  correspondence: 0.2-0.3 on these frames) is below `min_fitness` is replaced by the guess and
  counted in `DenseOdometryResult.failed_pairs`.
Speed: 150-350 ms per pair here on 2 busy shared cores (MEASURED.md: 47-71 ms on an idle machine).
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

__all__ = ["DenseOdometryError", "DenseOdometryResult", "dense_rgbd_odometry", "dense_rgbd_odometry_result"]

Method = Literal["point_to_plane", "hybrid", "intensity"]

_METHODS = {
    "point_to_plane": o3d.t.pipelines.odometry.Method.PointToPlane,
    "hybrid": o3d.t.pipelines.odometry.Method.Hybrid,
    "intensity": o3d.t.pipelines.odometry.Method.Intensity,
}
_CPU = o3c.Device("CPU:0")


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


def _rgbd(frame: RGBDFrame) -> o3d.t.geometry.RGBDImage:
    depth = np.nan_to_num(np.asarray(frame.depth, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    rgb = np.ascontiguousarray(frame.color, dtype=np.float32) / np.float32(255.0)  # [0, 1] for the Huber delta
    color = o3d.t.geometry.Image(o3c.Tensor(rgb, device=_CPU))
    return o3d.t.geometry.RGBDImage(color, o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth), device=_CPU)))


def dense_rgbd_odometry_result(
    frames: Iterable[RGBDFrame],
    *,
    method: Method = "point_to_plane",
    depth_max_m: float = 3.0,
    depth_diff_m: float = 0.03,
    depth_huber_delta_m: float = 0.02,
    intensity_huber_delta: float = 0.1,
    iterations: Sequence[int] = (10, 5, 3),
    constant_velocity: bool = True,
    photometric_init: Literal["point_to_plane", "guess"] = "point_to_plane",
    min_fitness: float = 0.05,
) -> DenseOdometryResult:
    """Frame-to-frame dense odometry with timings and per-pair fitness (see the module notes)."""
    if method not in _METHODS:
        raise DenseOdometryError(f"method must be one of {sorted(_METHODS)}, got {method!r}")
    if not (depth_max_m > 0 and depth_diff_m > 0 and depth_huber_delta_m > 0 and intensity_huber_delta > 0):
        raise DenseOdometryError("depth_max_m, depth_diff_m and the Huber deltas must be > 0")
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
            if not np.isfinite(T).all() or fit < min_fitness:
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
    "intensity"), depth_max_m, depth_diff_m, depth_huber_delta_m, intensity_huber_delta,
    iterations (per pyramid level, coarsest first), constant_velocity, photometric_init, min_fitness.
    Raises DenseOdometryError on unusable input (no depth, wrong dtype/shape, no frames).
    """
    r = dense_rgbd_odometry_result(frames, **kwargs)
    return r.stamps, r.poses
