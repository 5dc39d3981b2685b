"""Back end of single-side reconstruction: pose-graph optimisation and global BA.

Paper: "Single-Side Reconstruction", eq. (objectBA). Every pose is T_odom_cam
of the colour optical frame (x right, y down, z forward); lengths in metres,
pixels in px. Keys follow gtsam's examples: X(k) keyframe pose (gtsam.Pose3 of
T_odom_cam), L(j) landmark position (gtsam.Point3, odom).

Only GTSAM's built-in C++ factors are used (projection, stereo, between,
range, priors): a Python CustomFactor copies every variable on each call and
is far too slow at this size (docs/dependencies.md, "GTSAM 4.3.0 from Python").

RGB-D mode (paper: eta = 1, s_c = 1). The 3D term E_i compares the measured
point (pixel + aligned depth from the infrared stereo pair) with the
projected landmark. An aligned depth pixel is exactly a rectified stereo
observation: with a virtual baseline b, the right image column is
uR = uL - fx b / z. RealSense depth comes from stereo disparity, so its noise
is constant in disparity: sd(z) = z^2 sd_d / (fx b). Our depth model
sd(z) = 0.004 z^2 (m) therefore gives sd_d = 0.004 fx b (0.123 px for
fx = 615 px, b = 0.05 m), the default of `disparity_sigma`. The virtual
baseline itself does not change the solution (only sd_d / (fx b) matters).
Pixel and disparity noise are independent, so (uL, uR, v) has the full
covariance [[sp^2, sp^2, 0], [sp^2, sp^2 + sd^2, 0], [0, 0, sp^2]].
Observations without depth (0 = missing) get a plain projection factor.

RGB-only mode (eta = 0): projection factors only; the reconstruction is
defined up to a similarity, so the gauge has 7 degrees of freedom (see
`_add_gauge`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, replace
from typing import Literal, Sequence

import gtsam
import numpy as np
from gtsam.symbol_shorthand import L, X

from orchard_mapping.core.sidemap import LoopClosure, Observations
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import OrchardMappingError

__all__ = [
    "BAResult",
    "optimise_in_steps",
    "bundle_adjust_windowed",
    "ReconstructionError",
    "bundle_adjust",
    "default_disparity_sigma",
    "disparity_residual_sd",
    "optimise_pose_graph",
]

logger = logging.getLogger(__name__)

DEPTH_NOISE_COEFF = 0.004  # 1/m: depth sd = DEPTH_NOISE_COEFF * z^2 (RealSense-like)
GAUGE_SIGMA = 1e-6  # rad and m: "fixed" for the gauge priors
BRIDGE_MIN_OBSERVATIONS = 3  # a keyframe with fewer used observations is held to its neighbour


class ReconstructionError(OrchardMappingError):
    """Inputs of the reconstruction back end are inconsistent, or the optimiser failed."""


@dataclass(frozen=True)
class BAResult:
    """Outcome of `bundle_adjust`."""

    poses: np.ndarray  # (K, 4, 4) optimised T_odom_cam
    landmarks: np.ndarray  # (L, 3) m, odom; NaN where a landmark was not optimised
    initial_error: float  # factor-graph error (0.5 sum of robust whitened squares) at the start
    final_error: float  # ... at the solution
    iterations: int  # Levenberg-Marquardt iterations
    n_factors: int  # factors in the graph (priors included)
    n_landmarks_used: int  # landmarks that entered the graph
    seconds: float  # s, graph building + optimisation
    # px: robust sd (1.4826 MAD) of the disparity residuals at the solution (NaN: no depth term; windowed:
    # the largest of the windows'). How noisy the depth was, against the weights (docs/front_end.md).
    disparity_residual_sd: float = float("nan")


@dataclass(frozen=True)
class BundleAdjustmentParams:
    """Bundle-adjustment settings (config section `ba`), passed to `bundle_adjust` as keywords."""

    __pydantic_config__ = {"extra": "forbid"}  # config files: unknown keys are errors

    pixel_sigma: float = 1.0  # px, feature position noise
    # px. 0.123 px is the sensor's pure depth noise (0.004 z^2 with b = 0.05 m, fx = 615); depth sampled at
    # features also carries edge and quantisation error: 0.5 px gave lower ATE in half the iterations
    # (standard scenario, 15 Hz, 110 keyframes: ATE 0.037 % vs 0.043 % of path, 21 vs 50 iterations).
    disparity_sigma: float = 0.5
    baseline_m: float = 0.05  # m, virtual stereo baseline that turns depth into disparity
    huber_k: float = 1.345  # Huber threshold in sigmas
    loop_sigma_rot_deg: float = 1.0
    loop_sigma_trans_m: float = 0.02
    max_iterations: int = 30
    # Stop when an iteration lowers the error by less than this fraction. Huber's tail converges
    # linearly without moving the poses: 1e-3 stopped after 9 iterations with the drift and ATE of 30
    # (4-tree front side, 294 keyframes: 0.263 vs 0.262 % drift, 23 s vs 111 s).
    relative_error_tol: float = 1e-3
    min_observations: int = 2  # landmarks seen fewer times are left out
    # Bundle adjustment in windows of this many keyframes (0 = one global BA): memory is that of a window.
    # 30-tree row, 1535/1545 keyframes per side (front/back), with max_track 80 (docs/performance.md): the
    # BA's peak 1.80/1.82 GB (global, all observations) -> 1.14/0.92 GB, drift 0.258/0.091 -> 0.261/0.090 %,
    # ATE 0.049/0.044 -> 0.049/0.043 %. Windows of 300 (tail 80) cost the back side 8 % more drift.
    window: int = 500
    window_tail: int = 150  # keyframes at a window's end left to the next (~5 m: longer than a landmark's track)
    window_hold: int = 50  # adjusted keyframes a window starts from, held fixed (gauge and continuity)
    # Observations kept per landmark, spread evenly over its track (0 = all). Eliminating a landmark leaves a
    # dense factor on every keyframe that saw it, (6n)^2 for n views: where the camera turns at a row's end
    # landmarks are seen by 100-150 keyframes. Tracks are 8 keyframes long in the median and 28 at the 90th
    # percentile, so 80 cuts only those: 40 saved more memory but cost the 30-tree back side 33 % more drift.
    max_track: int = 80


def default_disparity_sigma(fx: float, baseline_m: float) -> float:
    """Disparity sd (px) equivalent to depth sd = 0.004 z^2 m: 0.004 * fx * b."""
    return DEPTH_NOISE_COEFF * fx * baseline_m


# ----------------------------------------------------------------- validation


def _check_poses(poses: np.ndarray) -> np.ndarray:
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or poses.shape[0] < 1:
        raise ReconstructionError(f"poses must be (K, 4, 4) with K >= 1, got shape {poses.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(poses), axis=(1, 2)))
    if bad.size:
        raise ReconstructionError(f"poses of keyframes {bad[:10].tolist()} are not finite")
    return poses


def _check_loops(loops: Sequence[LoopClosure], n_poses: int) -> None:
    for i, lc in enumerate(loops):
        for kf in (lc.kf_a, lc.kf_b):
            if not 0 <= int(kf) < n_poses:
                raise ReconstructionError(
                    f"loop closure {i} ({lc.kf_a} -> {lc.kf_b}) names keyframe {kf}, "
                    f"but there are {n_poses} keyframes"
                )
        T = np.asarray(lc.T_a_b, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ReconstructionError(f"loop closure {i} ({lc.kf_a} -> {lc.kf_b}): T_a_b must be a finite (4, 4)")


def _check_observations(obs: Observations, n_poses: int, n_landmarks: int) -> tuple[np.ndarray, ...]:
    kf = np.asarray(obs.keyframe)
    lm = np.asarray(obs.landmark)
    uv = np.asarray(obs.uv, dtype=float)
    depth = np.asarray(obs.depth, dtype=float)
    m = kf.shape[0] if kf.ndim == 1 else -1
    if kf.ndim != 1 or lm.shape != (m,) or uv.shape != (m, 2) or depth.shape != (m,):
        raise ReconstructionError(
            "observations must be keyframe (M,), landmark (M,), uv (M, 2), depth (M,); got "
            f"{kf.shape}, {lm.shape}, {uv.shape}, {depth.shape}"
        )
    if m and not (np.issubdtype(kf.dtype, np.integer) and np.issubdtype(lm.dtype, np.integer)):
        raise ReconstructionError(f"observation ids must be integers, got {kf.dtype} and {lm.dtype}")
    bad = np.flatnonzero((kf < 0) | (kf >= n_poses))
    if bad.size:
        raise ReconstructionError(
            f"observation {bad[0]} names keyframe {kf[bad[0]]}, but there are {n_poses} keyframes "
            f"({bad.size} such observations)"
        )
    bad = np.flatnonzero((lm < 0) | (lm >= n_landmarks))
    if bad.size:
        raise ReconstructionError(
            f"observation {bad[0]} names landmark {lm[bad[0]]}, but there are {n_landmarks} landmarks "
            f"({bad.size} such observations)"
        )
    bad = np.flatnonzero(~np.all(np.isfinite(uv), axis=1) | ~np.isfinite(depth) | (depth < 0.0))
    if bad.size:
        raise ReconstructionError(
            f"observation {bad[0]} (keyframe {kf[bad[0]]}, landmark {lm[bad[0]]}) has non-finite pixels "
            f"or a negative / non-finite depth ({bad.size} such observations)"
        )
    return kf.astype(np.int64), lm.astype(np.int64), uv, depth


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not np.isfinite(value) or value <= 0.0:
        raise ReconstructionError(f"{name} must be a positive number, got {value}")
    return value


# -------------------------------------------------------------- noise models


def _robust(base: gtsam.noiseModel.Base, huber_k: float | None) -> gtsam.noiseModel.Base:
    """Huber on the whitened residual (k in sigmas); None keeps the Gaussian model."""
    if huber_k is None:
        return base
    return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(float(huber_k)), base)


def _pose_sigmas(rot_deg: float, trans_m: float) -> gtsam.noiseModel.Diagonal:
    # Pose3 tangent order: rotation (rad) first, then translation (m).
    return gtsam.noiseModel.Diagonal.Sigmas(
        np.array([np.radians(rot_deg)] * 3 + [trans_m] * 3, dtype=float)
    )


def _gauge_prior(key: int, pose: np.ndarray) -> gtsam.PriorFactorPose3:
    # Gauge: the map frame odom_<side> is the first keyframe's camera frame; the
    # measurements only fix relative geometry, so keyframe 0 is held where it is.
    return gtsam.PriorFactorPose3(key, gtsam.Pose3(pose), gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA))


def _add_loops(
    graph: gtsam.NonlinearFactorGraph,
    loops: Sequence[LoopClosure],
    rot_deg: float,
    trans_m: float,
    huber_k: float | None,
) -> None:
    noise = _robust(_pose_sigmas(rot_deg, trans_m), huber_k)
    for lc in loops:
        # T_a_b = T_odom_a^-1 T_odom_b, exactly what BetweenFactorPose3(X(a), X(b)) measures.
        graph.add(gtsam.BetweenFactorPose3(X(int(lc.kf_a)), X(int(lc.kf_b)), gtsam.Pose3(np.asarray(lc.T_a_b)), noise))


def optimise_in_steps(optimizer: gtsam.NonlinearOptimizer, params: gtsam.NonlinearOptimizerParams) -> gtsam.Values:
    """optimizer.optimize(), one iteration per call into GTSAM, with GTSAM's own stopping rule (the same
    result, tests). GTSAM holds the GIL for the whole of a call: an optimize() of 3000 poses (11 s) let no
    other thread of the process run, so the odometry node, bundle-adjusting a finished side while it tracks
    the next, stopped taking camera frames and DDS dropped 22 of them (a 2-tree row at 1x). Between
    iterations the other threads run."""
    current = optimizer.error()
    if current <= params.getErrorTol() or optimizer.iterations() >= params.getMaxIterations():
        return optimizer.values()
    new = current
    while True:
        current = new
        optimizer.iterate()
        new = optimizer.error()
        if (optimizer.iterations() >= params.getMaxIterations() or not math.isfinite(current)
                or gtsam.checkConvergence(params, current, new)):
            return optimizer.values()


def _optimise(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, max_iterations: int, what: str,
    relative_error_tol: float = 1e-5,
) -> tuple[gtsam.Values, float, float, int]:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(max_iterations))
    # Stop when an iteration lowers the error by less than relative_error_tol: with Huber the
    # tail converges linearly and further iterations no longer move the poses.
    params.setRelativeErrorTol(float(relative_error_tol))
    params.setAbsoluteErrorTol(1e-6)
    initial_error = float(graph.error(initial))
    try:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        result = optimise_in_steps(optimizer, params)
    except RuntimeError as err:  # gtsam's C++ exceptions (indeterminant system, cheirality, ...)
        raise ReconstructionError(f"{what}: optimisation failed: {err}") from err
    final_error = float(graph.error(result))
    iterations = int(optimizer.iterations())
    logger.info("%s: error %.6g -> %.6g in %d iterations", what, initial_error, final_error, iterations)
    return result, initial_error, final_error, iterations


def disparity_residual_sd(poses: np.ndarray, landmarks: np.ndarray, kf: np.ndarray, lm: np.ndarray,
                          depth: np.ndarray, fx: float, baseline_m: float) -> float:
    """Robust sd (1.4826 MAD, px) of the disparity residuals of the depth observations (depth > 0): measured
    disparity fx b / depth against that of the landmark in the keyframe. poses (K, 4, 4) T_odom_cam, landmarks
    (L, 3) odom; kf, lm, depth (M,) per observation. NaN with fewer than 10 usable ones."""
    use = (depth > 0) & np.isfinite(landmarks[lm]).all(axis=1)  # (M,)
    T_cam_odom = np.linalg.inv(poses[kf[use]])  # (n, 4, 4)
    z = np.einsum("nj,nj->n", T_cam_odom[:, 2, :3], landmarks[lm[use]]) + T_cam_odom[:, 2, 3]  # (n,) m
    ok = z > 1e-3
    r = fx * baseline_m * (1.0 / depth[use][ok] - 1.0 / z[ok])  # (n,) px
    if len(r) < 10:
        return float("nan")
    return float(1.4826 * np.median(np.abs(r - np.median(r))))


def _poses_from(values: gtsam.Values, n: int) -> np.ndarray:
    return np.stack([values.atPose3(X(k)).matrix() for k in range(n)])  # (K, 4, 4)


# ----------------------------------------------------------------- pose graph


def optimise_pose_graph(
    poses: np.ndarray,
    loops: Sequence[LoopClosure],
    *,
    sigma_rot_deg: float = 0.5,
    sigma_trans_m: float = 0.01,
    loop_sigma_rot_deg: float = BundleAdjustmentParams.loop_sigma_rot_deg,
    loop_sigma_trans_m: float = BundleAdjustmentParams.loop_sigma_trans_m,
    huber_k: float | None = BundleAdjustmentParams.huber_k,
    max_iterations: int = 100,
) -> np.ndarray:
    """Pose-graph optimisation (paper: before global BA, to close loops).

    poses: (K, 4, 4) front-end T_odom_cam; consecutive relative poses become
    BetweenFactorPose3 with (sigma_rot_deg, sigma_trans_m); each loop closure a
    Huber-robust BetweenFactorPose3 from `T_a_b`. Returns (K, 4, 4) poses.
    """
    poses = _check_poses(poses)
    _check_loops(loops, len(poses))
    sigma_rot_deg = _positive("sigma_rot_deg", sigma_rot_deg)
    sigma_trans_m = _positive("sigma_trans_m", sigma_trans_m)
    loop_sigma_rot_deg = _positive("loop_sigma_rot_deg", loop_sigma_rot_deg)
    loop_sigma_trans_m = _positive("loop_sigma_trans_m", loop_sigma_trans_m)
    n = len(poses)

    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    pose3 = [gtsam.Pose3(T) for T in poses]
    for k, p in enumerate(pose3):
        initial.insert(X(k), p)
    graph.add(_gauge_prior(X(0), poses[0]))
    odom_noise = _pose_sigmas(sigma_rot_deg, sigma_trans_m)
    for k in range(n - 1):
        graph.add(gtsam.BetweenFactorPose3(X(k), X(k + 1), pose3[k].between(pose3[k + 1]), odom_noise))
    _add_loops(graph, loops, loop_sigma_rot_deg, loop_sigma_trans_m, huber_k)

    result, _, _, _ = _optimise(graph, initial, max_iterations, f"pose graph ({n} keyframes, {len(loops)} loops)")
    return _poses_from(result, n)


# ---------------------------------------------------------- bundle adjustment


def _add_gauge(
    graph: gtsam.NonlinearFactorGraph, poses: np.ndarray, mode: str, scale_anchor: int | None
) -> None:
    graph.add(_gauge_prior(X(0), poses[0]))
    if mode == "rgb" and scale_anchor is not None:
        # RGB only, the map is scale free: the 7th gauge freedom (scale) is fixed by
        # holding the distance from keyframe 0 to the keyframe farthest from it at its
        # initial value. A range factor fixes exactly that one freedom and, unlike a
        # prior on a keyframe's position, does not pull its direction towards the
        # (drifted) initial estimate. The farthest keyframe gives the best-conditioned
        # baseline.
        dist = float(np.linalg.norm(poses[scale_anchor, :3, 3] - poses[0, :3, 3]))
        graph.add(
            gtsam.RangeFactorPose3(X(0), X(scale_anchor), dist, gtsam.noiseModel.Isotropic.Sigma(1, GAUGE_SIGMA))
        )


def _spread_over_track(kf: np.ndarray, lm: np.ndarray, max_track: int) -> np.ndarray:
    """(M,) bool: at most max_track observations of each landmark, evenly spaced in keyframe order (0 = all)."""
    if max_track <= 0:
        return np.ones(len(kf), bool)
    if max_track < 2:
        raise ReconstructionError(f"max_track must be 0 (all) or >= 2, got {max_track}")
    order = np.lexsort((kf, lm))  # by landmark, then keyframe
    lm_s = lm[order]
    starts = np.flatnonzero(np.r_[True, lm_s[1:] != lm_s[:-1]])  # (G,) first row of each landmark
    count = np.diff(np.r_[starts, len(lm_s)])  # (G,)
    c = np.repeat(count, count)  # (M,) the track length of each row's landmark
    r = np.arange(len(lm_s)) - np.repeat(starts, count)  # (M,) rank along the track
    slot = np.rint(r * (max_track - 1) / np.maximum(c - 1, 1))  # the evenly spaced slot nearest to r
    pick = np.rint(slot * (c - 1) / (max_track - 1)) == r  # r is that slot's own observation
    keep = np.empty(len(kf), bool)
    keep[order] = (c <= max_track) | pick
    return keep


def bundle_adjust(
    poses: np.ndarray,
    landmarks: np.ndarray,
    obs: Observations,
    intr: CameraIntrinsics,
    *,
    mode: Literal["rgbd", "rgb"] = "rgbd",
    loops: Sequence[LoopClosure] = (),
    pixel_sigma: float = BundleAdjustmentParams.pixel_sigma,
    disparity_sigma: float | None = BundleAdjustmentParams.disparity_sigma,
    baseline_m: float = BundleAdjustmentParams.baseline_m,
    huber_k: float | None = BundleAdjustmentParams.huber_k,
    loop_sigma_rot_deg: float = BundleAdjustmentParams.loop_sigma_rot_deg,
    loop_sigma_trans_m: float = BundleAdjustmentParams.loop_sigma_trans_m,
    bridge_sigma_rot_deg: float = 1.0,
    bridge_sigma_trans_m: float = 0.05,
    max_iterations: int = BundleAdjustmentParams.max_iterations,
    min_observations: int = BundleAdjustmentParams.min_observations,
    relative_error_tol: float = BundleAdjustmentParams.relative_error_tol,
    scale_anchor: int | None = None,
    hold: Sequence[int] = (),
    max_track: int = BundleAdjustmentParams.max_track,
) -> BAResult:
    """Global bundle adjustment, eq. (objectBA), with Huber on every term.

    poses: (K, 4, 4) initial T_odom_cam; landmarks: (L, 3) initial positions
    in odom (NaN rows are left out); obs: observations of landmarks at
    keyframes. mode "rgbd": stereo factors where depth > 0 (see module doc),
    projection factors elsewhere; "rgb": projection factors only (depth
    ignored), scale fixed by a range prior. pixel_sigma (px) and
    disparity_sigma (px; None = 0.004 fx baseline_m, i.e. depth sd
    0.004 z^2 m) weight the terms; huber_k in sigmas (None = no robust
    kernel). Landmarks with fewer than `min_observations` observations are
    left out. A keyframe left with fewer than 3 observations is tied to the
    previous one by its initial relative pose (bridge sigmas), so the system
    stays determined. Loop closures enter as robust BetweenFactorPose3.
    scale_anchor (rgb): the keyframe whose distance to keyframe 0 keeps its initial value (the scale gauge);
    None = the keyframe farthest from keyframe 0.
    hold (rgbd): keyframes held at their initial poses instead of keyframe 0 alone (the gauge of a window
    continuing an adjusted part: `bundle_adjust_windowed`).
    max_track: at most this many observations per landmark, spread evenly over the keyframes that saw it,
    first and last included (0 = all).
    """
    t0 = time.perf_counter()
    if mode not in ("rgbd", "rgb"):
        raise ReconstructionError(f"mode must be 'rgbd' or 'rgb', got {mode!r}")
    poses = _check_poses(poses)
    landmarks = np.asarray(landmarks, dtype=float)
    if landmarks.ndim != 2 or landmarks.shape[1] != 3:
        raise ReconstructionError(f"landmarks must be (L, 3), got shape {landmarks.shape}")
    n_kf, n_lm = len(poses), len(landmarks)
    kf, lm, uv, depth = _check_observations(obs, n_kf, n_lm)
    _check_loops(loops, n_kf)
    pixel_sigma = _positive("pixel_sigma", pixel_sigma)
    baseline_m = _positive("baseline_m", baseline_m)
    if disparity_sigma is None:
        disparity_sigma = default_disparity_sigma(intr.fx, baseline_m)
    disparity_sigma = _positive("disparity_sigma", disparity_sigma)
    if intr.fx <= 0 or intr.fy <= 0:
        raise ReconstructionError(f"intrinsics need positive focal lengths, got fx={intr.fx}, fy={intr.fy}")
    if mode == "rgb":
        depth = np.zeros_like(depth)  # eta = 0: the 3D term is off

    # Landmarks used: a finite initial position and enough observations.
    counts = np.bincount(lm, minlength=n_lm)  # (L,)
    used_lm = (counts >= int(min_observations)) & np.all(np.isfinite(landmarks), axis=1)  # (L,)
    keep = used_lm[lm] & _spread_over_track(kf, lm, int(max_track))  # (M,)
    kf, lm, uv, depth = kf[keep], lm[keep], uv[keep], depth[keep]
    if not np.any(used_lm):
        raise ReconstructionError(
            f"no landmark has a finite initial position and >= {min_observations} observations "
            f"({n_lm} landmarks, {len(obs)} observations)"
        )

    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    for k in range(n_kf):
        initial.insert(X(k), gtsam.Pose3(poses[k]))
    for j in np.flatnonzero(used_lm):
        initial.insert(L(int(j)), gtsam.Point3(*landmarks[j]))

    # One factor per observation: gtsam's Python API builds factors one by one.
    K_mono = gtsam.Cal3_S2(intr.fx, intr.fy, 0.0, intr.cx, intr.cy)
    K_stereo = gtsam.Cal3_S2Stereo(intr.fx, intr.fy, 0.0, intr.cx, intr.cy, baseline_m)
    mono_noise = _robust(gtsam.noiseModel.Isotropic.Sigma(2, pixel_sigma), huber_k)
    sp2, sd2 = pixel_sigma**2, disparity_sigma**2
    stereo_cov = np.array([[sp2, sp2, 0.0], [sp2, sp2 + sd2, 0.0], [0.0, 0.0, sp2]])  # (uL, uR, v)
    stereo_noise = _robust(gtsam.noiseModel.Gaussian.Covariance(stereo_cov), huber_k)
    has_depth = depth > 0.0  # (M,)
    u_right = uv[:, 0] - np.divide(intr.fx * baseline_m, depth, out=np.zeros_like(depth), where=has_depth)  # (M,)
    for i in range(len(kf)):
        xk, lj = X(int(kf[i])), L(int(lm[i]))
        if has_depth[i]:
            meas = gtsam.StereoPoint2(uv[i, 0], u_right[i], uv[i, 1])
            graph.add(gtsam.GenericStereoFactor3D(meas, stereo_noise, xk, lj, K_stereo))
        else:
            graph.add(gtsam.GenericProjectionFactorCal3_S2(uv[i], mono_noise, xk, lj, K_mono))

    if mode == "rgb":
        if n_kf < 2:
            raise ReconstructionError("RGB-only bundle adjustment needs at least 2 keyframes")
        dist = np.linalg.norm(poses[:, :3, 3] - poses[0, :3, 3], axis=1)  # (K,)
        if scale_anchor is None:
            scale_anchor = int(np.argmax(dist))
        if not 0 < scale_anchor < n_kf:
            raise ReconstructionError(f"scale_anchor {scale_anchor} is not a keyframe other than 0 (0..{n_kf - 1})")
        if dist[scale_anchor] < 1e-6:
            raise ReconstructionError("RGB-only bundle adjustment: all keyframes at one position, scale undefined")
    if hold and mode == "rgbd":
        for k in hold:
            graph.add(_gauge_prior(X(int(k)), poses[int(k)]))
    else:
        _add_gauge(graph, poses, mode, scale_anchor)

    # Keyframes the observations leave (nearly) undetermined are tied to the previous one.
    per_kf = np.bincount(kf, minlength=n_kf)  # (K,)
    weak = [k for k in range(1, n_kf) if per_kf[k] < BRIDGE_MIN_OBSERVATIONS]
    if weak:
        logger.warning(
            "bundle adjustment: keyframes %s have < %d observations, tied to their predecessor",
            weak[:10],
            BRIDGE_MIN_OBSERVATIONS,
        )
        bridge = _pose_sigmas(bridge_sigma_rot_deg, bridge_sigma_trans_m)
        for k in weak:
            rel = gtsam.Pose3(poses[k - 1]).between(gtsam.Pose3(poses[k]))
            graph.add(gtsam.BetweenFactorPose3(X(k - 1), X(k), rel, bridge))
    _add_loops(graph, loops, loop_sigma_rot_deg, loop_sigma_trans_m, huber_k)

    what = (
        f"bundle adjustment ({mode}: {n_kf} keyframes, {int(used_lm.sum())} landmarks, "
        f"{int(has_depth.sum())} stereo + {int((~has_depth).sum())} projection factors)"
    )
    result, e0, e1, iters = _optimise(graph, initial, max_iterations, what, relative_error_tol)

    out_lm = np.full((n_lm, 3), np.nan)  # (L, 3)
    for j in np.flatnonzero(used_lm):
        out_lm[j] = result.atPoint3(L(int(j)))
    out_poses = _poses_from(result, n_kf)
    seconds = time.perf_counter() - t0
    logger.info("%s: %.3f s", what, seconds)
    return BAResult(
        poses=out_poses,
        landmarks=out_lm,
        initial_error=e0,
        final_error=e1,
        iterations=iters,
        n_factors=int(graph.size()),
        n_landmarks_used=int(used_lm.sum()),
        seconds=seconds,
        disparity_residual_sd=disparity_residual_sd(out_poses, out_lm, kf, lm, depth, intr.fx, baseline_m),
    )


def bundle_adjust_windowed(
    poses: np.ndarray,
    landmarks: np.ndarray,
    obs: Observations,
    intr: CameraIntrinsics,
    *,
    window: int,
    window_tail: int,
    window_hold: int,
    mode: Literal["rgbd", "rgb"] = "rgbd",
    loops: Sequence[LoopClosure] = (),
    **kw,
) -> BAResult:
    """`bundle_adjust` (rgbd) in windows of `window` consecutive keyframes, so memory does not grow with the row.

    Each window holds its first `hold` keyframes, already final, at their adjusted poses (gauge and
    continuity), and leaves its last `tail` keyframes to the next window, which starts from this one's
    estimate of them: a keyframe is final once the keyframes after it that share landmarks with it are in
    the same window (a landmark is seen over ~1.5 m of path, ~60 keyframes at 15 Hz). Keyframes after the
    window start from the input poses moved rigidly with its last final keyframe. Loop closures within a
    window enter its graph; one that spans windows is kept by a last pose graph over the adjusted
    relative poses and the loops, which moves each keyframe's landmarks with it.
    """
    poses = _check_poses(poses)
    landmarks = np.asarray(landmarks, dtype=float)
    n_kf = len(poses)
    tail, hold = int(window_tail), int(window_hold)
    if window and not (0 < hold and 0 <= tail and window > hold + tail):
        raise ReconstructionError(f"windowed bundle adjustment needs 0 < window_hold and window > window_hold + "
                                  f"window_tail, got window={window}, window_tail={tail}, window_hold={hold}")
    if n_kf <= window or window == 0 or mode == "rgb":  # RGB only: one BA holds the scale gauge of the side
        return bundle_adjust(poses, landmarks, obs, intr, mode=mode, loops=loops, **kw)
    t0 = time.perf_counter()
    kf, lm, uv, depth = _check_observations(obs, n_kf, len(landmarks))
    out = poses.copy()  # (K, 4, 4) final up to `done`, then the current estimate
    out_lm = np.full_like(landmarks, np.nan)  # (L, 3)
    e0 = e1 = 0.0
    iters = n_factors = 0
    resid_sd = []  # per window
    a, done, last_b = 0, 0, 0
    used_loops: set[int] = set()
    while True:
        b = min(n_kf, a + window)
        init = out[a:b].copy()  # (W, 4, 4): final or estimated by the last window up to its end ...
        if 0 < last_b < b:  # ... then the input poses carried along by the last estimated keyframe
            init[last_b - a:] = out[last_b - 1] @ np.linalg.inv(poses[last_b - 1]) @ poses[last_b:b]
        sel = (kf >= a) & (kf < b)  # (M,) observations in the window
        ids, lm_local = np.unique(lm[sel], return_inverse=True)
        lm_init = np.where(np.isfinite(out_lm[ids]), out_lm[ids], landmarks[ids])  # (L_w, 3)
        # landmarks first estimated here follow the window's start correction
        fresh = ~np.isfinite(out_lm[ids]).all(axis=1)
        if a > 0:
            C = out[a] @ np.linalg.inv(poses[a])
            lm_init[fresh] = landmarks[ids[fresh]] @ C[:3, :3].T + C[:3, 3]
        sub = Observations(kf[sel] - a, lm_local, uv[sel], depth[sel])
        inside = [i for i, lc in enumerate(loops) if a <= lc.kf_a < b and a <= lc.kf_b < b]
        used_loops.update(inside)
        win_loops = [replace(loops[i], kf_a=loops[i].kf_a - a, kf_b=loops[i].kf_b - a) for i in inside]
        res = bundle_adjust(init, lm_init, sub, intr, mode=mode, loops=win_loops,
                            hold=range(done - a) if a else range(1), **kw)
        out[max(done, a):b] = res.poses[max(done, a) - a:]
        ok = np.isfinite(res.landmarks).all(axis=1)
        out_lm[ids[ok]] = res.landmarks[ok]
        e0, e1 = e0 + res.initial_error, e1 + res.final_error
        iters, n_factors = max(iters, res.iterations), n_factors + res.n_factors
        resid_sd.append(res.disparity_residual_sd)
        last_b = b
        if b == n_kf:
            break
        done = b - tail
        a = done - hold
    spanning = [lc for i, lc in enumerate(loops) if i not in used_loops]
    if spanning:  # the last pass over the reduced problem: keyframe poses only
        before = out
        out = optimise_pose_graph(out, spanning, loop_sigma_rot_deg=kw.get("loop_sigma_rot_deg", BundleAdjustmentParams.loop_sigma_rot_deg),
                                  loop_sigma_trans_m=kw.get("loop_sigma_trans_m", BundleAdjustmentParams.loop_sigma_trans_m))
        first = np.full(len(landmarks), n_kf)
        np.minimum.at(first, lm, kf)  # (L,) each landmark's first observing keyframe
        ok = (first < n_kf) & np.isfinite(out_lm).all(axis=1)
        M = out[first[ok]] @ np.linalg.inv(before[first[ok]])  # (n, 4, 4) how that keyframe moved
        out_lm[ok] = np.einsum("nij,nj->ni", M[:, :3, :3], out_lm[ok]) + M[:, :3, 3]
    seconds = time.perf_counter() - t0
    logger.info("windowed bundle adjustment (%d keyframes, windows of %d): %.3f s", n_kf, window, seconds)
    return BAResult(poses=out, landmarks=out_lm, initial_error=e0, final_error=e1, iterations=iters,
                    n_factors=n_factors, n_landmarks_used=int(np.isfinite(out_lm).all(axis=1).sum()), seconds=seconds,
                    disparity_residual_sd=float(np.nanmax(resid_sd)) if np.isfinite(resid_sd).any() else float("nan"))
