"""Pure metric functions on arrays (definitions: docs/results.md, "Metric definitions").

Each returns a frozen dataclass whose field names (with their units) are the
keys the evaluation report serialises.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from orchard_mapping.core.geometry import (
    decompose_similarity,
    path_length,
    pose_matrices,
    rotation_angle_deg,
    transform_points,
    umeyama,
)
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.errors import AlignmentError

__all__ = [
    "DoubleCount",
    "MergeError",
    "TrajectoryError",
    "TreeMatching",
    "associate_stamps",
    "double_count",
    "fit_map_to_world",
    "map_merge_error",
    "match_trees",
    "merge_error",
    "rigid_rmse_mm",
    "trajectory_between",
    "trajectory_error",
]


@dataclass(frozen=True)
class TreeMatching:
    """One-to-one assignment of estimated trees to true trees."""

    true_index: np.ndarray  # (K,) int, into the true trees
    est_index: np.ndarray  # (K,) int, into the estimated trees
    distance_m: np.ndarray  # (K,) m, 3D
    missed: np.ndarray  # (M,) int, true trees without an estimate
    false: np.ndarray  # (P,) int, estimates without a true tree


def match_trees(true_xyz: np.ndarray, est_xyz: np.ndarray, radius_m: float) -> TreeMatching:
    """Hungarian assignment on 3D distance (T, 3) x (E, 3); pairs farther than radius_m are dropped."""
    true_xyz = np.asarray(true_xyz, dtype=float).reshape(-1, 3)
    est_xyz = np.asarray(est_xyz, dtype=float).reshape(-1, 3)
    d = np.linalg.norm(true_xyz[:, None, :] - est_xyz[None, :, :], axis=2)  # (T, E)
    if d.size:
        big = 1e6 * (1.0 + float(d.max()))
        rows, cols = linear_sum_assignment(np.where(d <= radius_m, d, big))
        keep = d[rows, cols] <= radius_m
        rows, cols = rows[keep], cols[keep]
    else:
        rows = cols = np.zeros(0, dtype=int)
    return TreeMatching(
        true_index=rows,
        est_index=cols,
        distance_m=d[rows, cols] if d.size else np.zeros(0),
        missed=np.setdiff1d(np.arange(true_xyz.shape[0]), rows),
        false=np.setdiff1d(np.arange(est_xyz.shape[0]), cols),
    )


@dataclass(frozen=True)
class DoubleCount:
    """Estimated fruit vs true fruit (both in map)."""

    estimated: int  # estimated fruit positions
    matched: int  # estimates whose nearest true fruit is within the gate
    unique_true: int  # distinct true fruit claimed
    duplicates: int  # estimates whose true fruit was already claimed by another estimate
    false: int  # estimates with no true fruit within the gate
    rate_percent: float | None  # duplicates / estimated x 100
    gate_factor: float  # gate = gate_factor x the true fruit's radius
    position_error_median_mm: float | None = None  # mm, matched estimates to their true fruit's centre
    diameter_mae_mm: float | None = None  # mm, matched estimates with a diameter
    diameter_bias_mm: float | None = None  # mm, signed mean of the same
    # duplicates per 100 true fruit seen from both sides (the ones a two-side count can count twice)
    per_both_percent: float | None = None


def double_count(
    est_xyz: np.ndarray, true_xyz: np.ndarray, true_radius_m: np.ndarray, gate_factor: float = 1.5,
    est_diameter_m: np.ndarray | None = None, true_seen_from_both: int | None = None,
) -> DoubleCount:
    """Each estimate claims its nearest true fruit if within gate_factor x that fruit's radius.

    A true fruit claimed by k > 1 estimates contributes k - 1 duplicates
    (independent of the order of the estimates). est_diameter_m (n,; NaN unknown): scored against twice the
    claimed fruit's radius. true_seen_from_both: the true fruit visible from both sides (per_both_percent).
    """
    est_xyz = np.asarray(est_xyz, dtype=float).reshape(-1, 3)
    true_xyz = np.asarray(true_xyz, dtype=float).reshape(-1, 3)
    radii = np.asarray(true_radius_m, dtype=float).reshape(-1)
    n = est_xyz.shape[0]
    if n == 0 or true_xyz.shape[0] == 0:
        return DoubleCount(n, 0, 0, 0, n, 0.0 if n else None, gate_factor)
    dist, idx = cKDTree(true_xyz).query(est_xyz)  # (n,), (n,)
    hit = dist <= gate_factor * radii[idx]
    claimed = np.bincount(idx[hit], minlength=true_xyz.shape[0])  # (F,)
    unique = int(np.count_nonzero(claimed))
    dup = int(hit.sum()) - unique
    dia_err = None
    if est_diameter_m is not None:
        e = np.asarray(est_diameter_m, float).reshape(-1)[hit] - 2.0 * radii[idx[hit]]
        dia_err = e[np.isfinite(e)]
    return DoubleCount(
        estimated=n,
        matched=int(hit.sum()),
        unique_true=unique,
        duplicates=dup,
        false=int(n - hit.sum()),
        rate_percent=100.0 * dup / n,
        gate_factor=gate_factor,
        position_error_median_mm=float(1000 * np.median(dist[hit])) if hit.any() else None,
        diameter_mae_mm=float(1000 * np.mean(np.abs(dia_err))) if dia_err is not None and len(dia_err) else None,
        diameter_bias_mm=float(1000 * np.mean(dia_err)) if dia_err is not None and len(dia_err) else None,
        per_both_percent=100.0 * dup / true_seen_from_both if true_seen_from_both else None,
    )


@dataclass(frozen=True)
class MergeError:
    """Estimated vs true T_front_back."""

    rotation_error_deg: float  # deg, angle of R_true^T R_est (scale removed)
    translation_error_mm: float  # mm, mean |T_est p - T_true p| over true trunk bases p in odom_back
    max_translation_error_mm: float  # mm, the largest of those
    n_points: int  # trunk bases used
    scale: float  # estimated scale s (1 = rigid)
    scale_error_percent: float | None  # (s - 1) x 100; None when the estimate is rigid


def merge_error(T_est: np.ndarray, T_true: np.ndarray, points_back: np.ndarray) -> MergeError:
    """Compare two odom_back -> odom_front transforms (4, 4); points_back (P, 3) m in odom_back."""
    est = decompose_similarity(T_est)
    true = decompose_similarity(T_true)
    pts = np.asarray(points_back, dtype=float).reshape(-1, 3)
    if pts.shape[0] == 0:
        raise AlignmentError("merge error needs at least one trunk base point")
    err = np.linalg.norm(transform_points(T_est, pts) - transform_points(T_true, pts), axis=1)  # (P,)
    rigid = abs(est.s - 1.0) < 1e-9
    return MergeError(
        rotation_error_deg=rotation_angle_deg(true.R.T @ est.R),
        translation_error_mm=1000.0 * float(err.mean()),
        max_translation_error_mm=1000.0 * float(err.max()),
        n_points=int(pts.shape[0]),
        scale=float(est.s),
        scale_error_percent=None if rigid else 100.0 * (est.s - 1.0),
    )


# m: without scene points, each keyframe joins the fit as its centre and the points this far along its camera
# axes. A side's keyframe centres lie nearly on one line (the row), which leaves the roll about it free.
_AXIS_POINT_M = 1.0
# m: a scene point joins a keyframe's part of the fit when it lies in front of the camera and this close: the
# range of the fused depth (fusion.depth_max_m, 3 m by default) and a margin.
SCENE_VIEW_RANGE_M = 4.0


def _pose_points(T: np.ndarray) -> np.ndarray:
    """(4K, 3): each pose's centre and the points _AXIS_POINT_M along its x, y and z axes; T (K, 4, 4)."""
    c = T[:, :3, 3]
    return np.concatenate([c] + [c + _AXIS_POINT_M * T[:, :3, a] for a in range(3)])


def _seen_points(T_est: np.ndarray, T_true: np.ndarray, scene: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(placed (M, 3), true (M, 3)): every scene point (S, 3) world that a keyframe sees (in front of its true
    camera within SCENE_VIEW_RANGE_M), where the keyframe's estimated pose (K, 4, 4) map puts it, and where
    it is. A keyframe misplaces what it sees by its position error plus its orientation error times the
    distance: these pairs weigh the two as the map does."""
    local = np.einsum("kji,ksj->ksi", T_true[:, :3, :3], scene[None] - T_true[:, None, :3, 3])  # (K, S, 3) cam
    seen = (local[..., 2] > 0.1) & (np.linalg.norm(local, axis=2) < SCENE_VIEW_RANGE_M)  # (K, S)
    placed = np.einsum("kij,ksj->ksi", T_est[:, :3, :3], local) + T_est[:, None, :3, 3]  # (K, S, 3) map
    return placed[seen], np.broadcast_to(scene, local.shape)[seen]


def fit_map_to_world(est: StampedTrajectory, true: StampedTrajectory, T_world_odom: np.ndarray,
                     max_dt_s: float, scene_points: np.ndarray | None = None) -> np.ndarray:
    """(4, 4) the rigid map -> world transform that best fits a side's map to the truth: with scene_points
    (S, 3) world, what each keyframe sees of them placed by its estimated pose against where they are (the
    map's own content; _seen_points); without them, or when fewer than 3 are seen, the keyframes' poses
    (centres and axis points)."""
    order_t = np.argsort(true.stamps, kind="stable")
    order_e = np.argsort(est.stamps, kind="stable")
    i_s, j_s = associate_stamps(np.asarray(est.stamps)[order_e], np.asarray(true.stamps)[order_t], max_dt_s)
    i, j = order_e[i_s], order_t[j_s]
    if i.size < 2:
        raise AlignmentError(f"{true.frame_id or 'a side'}: {i.size} keyframes paired with the true trajectory "
                             "by stamp; the merged map's error needs 2")
    T_est = pose_matrices(np.asarray(est.positions)[i], np.asarray(est.quaternions)[i])  # (n, 4, 4) map
    T_true = T_world_odom @ pose_matrices(np.asarray(true.positions)[j], np.asarray(true.quaternions)[j])  # world
    if scene_points is not None:
        placed, where = _seen_points(T_est, T_true, np.asarray(scene_points, float).reshape(-1, 3))
        if len(placed) >= 3:
            return umeyama(placed, where).matrix()
    return umeyama(_pose_points(T_est), _pose_points(T_true)).matrix()


def map_merge_error(front_map: StampedTrajectory, back_map: StampedTrajectory, front_true: StampedTrajectory,
                    back_true: StampedTrajectory, T_world_front: np.ndarray, T_world_back: np.ndarray,
                    points_world: np.ndarray, max_dt_s: float = 0.005,
                    scene_points: np.ndarray | None = None) -> MergeError:
    """Where the merged map puts the back side against where it puts the front side, each side's own
    drift left out (docs/results.md): each side's map is fitted to the truth by one rigid transform,
    A_front and A_back (fit_map_to_world, on the scene_points (S, 3) world its keyframes see: the true
    trunk bases and tops). A perfect merge of two drifted sides has A_front = A_back (both sides bent
    alike); the back side is misplaced by D = A_front A_back^-1. Rotation: the angle of D; translation:
    |D p - p| over points_world (P, 3) m (the true trunk bases). The true poses of each side are in its
    odom frame, T_world_<side> (4, 4) places them in world."""
    A_f = fit_map_to_world(front_map, front_true, T_world_front, max_dt_s, scene_points)
    A_b = fit_map_to_world(back_map, back_true, T_world_back, max_dt_s, scene_points)
    D = A_f @ np.linalg.inv(A_b)
    pts = np.asarray(points_world, dtype=float).reshape(-1, 3)
    if pts.shape[0] == 0:
        raise AlignmentError("merge error needs at least one trunk base point")
    err = np.linalg.norm(transform_points(D, pts) - pts, axis=1)  # (P,)
    return MergeError(rotation_error_deg=rotation_angle_deg(D[:3, :3]), translation_error_mm=1000.0 * float(err.mean()),
                      max_translation_error_mm=1000.0 * float(err.max()), n_points=int(pts.shape[0]), scale=1.0,
                      scale_error_percent=None)


def trajectory_between(traj: StampedTrajectory, t0: float, t1: float) -> StampedTrajectory:
    """The poses of traj stamped within [t0, t1] s (e.g. a side's sweep that saw its trunks: the stamps of
    its first and last trunk observation)."""
    st = np.asarray(traj.stamps, float)
    keep = (st >= t0) & (st <= t1)
    return StampedTrajectory(st[keep], np.asarray(traj.positions)[keep], np.asarray(traj.quaternions)[keep],
                             traj.frame_id)


def rigid_rmse_mm(est: np.ndarray, true: np.ndarray) -> float | None:
    """mm, RMS of |R est + t - true| after the best rigid alignment (Kabsch); None below 3 points."""
    if len(est) < 3:
        return None
    try:
        S = umeyama(est, true)
    except AlignmentError:  # the estimates coincide
        return None
    return float(1000 * np.sqrt(np.mean(np.sum((est @ (S.s * S.R).T + S.t - true) ** 2, axis=1))))


def associate_stamps(est_stamps: np.ndarray, true_stamps: np.ndarray, max_dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_est, i_true) pairing each estimated stamp with the nearest true stamp within max_dt_s.

    Both stamp arrays must increase. Each true stamp is used at most once
    (the first estimate keeps it).
    """
    est = np.asarray(est_stamps, dtype=float).reshape(-1)
    tru = np.asarray(true_stamps, dtype=float).reshape(-1)
    if est.size == 0 or tru.size == 0:
        return np.zeros(0, dtype=int), np.zeros(0, dtype=int)
    hi = np.clip(np.searchsorted(tru, est), 1, tru.size - 1) if tru.size > 1 else np.zeros(est.size, dtype=int)
    lo = np.maximum(hi - 1, 0)
    j = np.where(np.abs(tru[lo] - est) <= np.abs(tru[hi] - est), lo, hi)  # (N,)
    ok = np.abs(tru[j] - est) <= max_dt_s
    i_est, j = np.flatnonzero(ok), j[ok]
    _, first = np.unique(j, return_index=True)
    first.sort()
    return i_est[first], j[first]


@dataclass(frozen=True)
class TrajectoryError:
    """One side's estimated keyframe trajectory vs the true camera trajectory."""

    n_associated: int  # poses paired by stamp
    path_length_m: float | None  # m, true path over the associated span
    drift_mm: float | None  # mm, last position error after exact first-pose alignment
    drift_percent: float | None  # drift / path length x 100
    final_rotation_error_deg: float | None  # deg, last orientation error after first-pose alignment
    ate_mm: float | None  # mm, position RMSE after the best alignment
    ate_percent: float | None  # ATE / path length x 100
    alignment: str  # "se3" (rigid) or "sim3" (with scale) for the ATE
    alignment_scale: float | None  # fitted scale (1 for se3)


def trajectory_error(
    est: StampedTrajectory, true: StampedTrajectory, max_dt_s: float = 0.005, with_scale: bool = False
) -> TrajectoryError:
    """Drift (first pose aligned exactly) and ATE (Umeyama) of `est` against `true`.

    Rigid (se3): nothing is fitted for the drift. With scale (sim3, a colour-only side up to scale): the
    estimate's translations are first multiplied by the ATE fit's scale, so the drift is what the side got
    wrong beyond one global scale (without it a side in units of its first baseline reads as ~100 % drift).
    Needs 2 associated poses for the drift and 3 for the ATE (and for a sim3 drift); otherwise None.
    """
    order_t = np.argsort(true.stamps, kind="stable")
    order_e = np.argsort(est.stamps, kind="stable")
    i_s, j_s = associate_stamps(np.asarray(est.stamps)[order_e], np.asarray(true.stamps)[order_t], max_dt_s)
    i, j = order_e[i_s], order_t[j_s]
    n = int(i.size)
    none = TrajectoryError(n, None, None, None, None, None, None, "sim3" if with_scale else "se3", None)
    if n < 2:
        return none
    T_est = pose_matrices(np.asarray(est.positions)[i], np.asarray(est.quaternions)[i])  # (n, 4, 4)
    T_true = pose_matrices(np.asarray(true.positions)[j], np.asarray(true.quaternions)[j])  # (n, 4, 4)
    length = path_length(np.asarray(true.positions)[order_t][j_s.min() : j_s.max() + 1])

    def pct(v: float) -> float | None:
        return 100.0 * v / length if length > 1e-9 else None

    ate_mm = ate_pct = scale = None
    if n >= 3:
        try:
            sim = umeyama(T_est[:, :3, 3], T_true[:, :3, 3], with_scale=with_scale)
        except AlignmentError:
            sim = None
        if sim is not None:
            res = transform_points(sim.matrix(), T_est[:, :3, 3]) - T_true[:, :3, 3]  # (n, 3)
            rmse = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
            ate_mm, ate_pct, scale = 1000.0 * rmse, pct(rmse), float(sim.s)
    if with_scale:
        if scale is None:
            return none
        T_est = T_est.copy()
        T_est[:, :3, 3] *= scale
    # Drift: T_true0 inv(T_est0) applied to every estimated pose.
    T_align = T_true[0] @ np.linalg.inv(T_est[0])
    last = T_align @ T_est[-1]
    drift = float(np.linalg.norm(last[:3, 3] - T_true[-1][:3, 3]))
    rot = rotation_angle_deg(T_true[-1][:3, :3].T @ last[:3, :3])
    return TrajectoryError(
        n_associated=n,
        path_length_m=length,
        drift_mm=1000.0 * drift,
        drift_percent=pct(drift),
        final_rotation_error_deg=rot,
        ate_mm=ate_mm,
        ate_percent=ate_pct,
        alignment=none.alignment,
        alignment_scale=scale,
    )
