"""Trunk and local-ground metrics of one side against the simulator's ground truth.

Each result trunk lives in its side's reconstruction frame, which drifts a
little along the row. The trunk's geometry (diameter, axis, its ground) is
what is measured here, not the drift (the trajectory metrics measure that):
every trunk is taken into the world through its own local alignment, the true
camera pose times the inverse of the estimated one at the trunk's median
observation stamp.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from orchard_mapping.core.geometry import pose_matrices
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.eval.ground_truth import GroundTruth, TrueTree
from orchard_mapping.io.landmarks import ResultGround, ResultTrunk

__all__ = ["GroundErrors", "TrunkErrors", "TrunkPair", "ground_errors", "trunk_errors"]

TRUNK_MATCH_RADIUS_M = 0.15  # m across the row direction (x, y in world): a reported trunk is that tree's


@dataclass(frozen=True)
class TrunkPair:
    true_id: int
    trunk_id: int
    distance_m: float  # m, horizontal, world
    diameter_true_mm: float
    diameter_mm: float | None
    diameter_3d_only_mm: float | None
    axis_error_deg: float
    flags: tuple[str, ...] = ()


@dataclass(frozen=True)
class TrunkErrors:
    true_in_view: int  # true trunks this side saw at the diameter height
    reported: int
    matched: int  # reported trunks within TRUNK_MATCH_RADIUS_M of a true trunk
    recall: float | None  # matched true trunks in view / true trunks in view
    precision: float | None  # matched reported / reported
    diameter_n: int
    diameter_mae_mm: float | None
    diameter_bias_mm: float | None  # mean of estimate - truth
    diameter_3d_only_mae_mm: float | None  # the 3D-only fit of the same bands (the paper's baseline)
    diameter_3d_only_bias_mm: float | None
    axis_error_deg: float | None  # median over matched trunks
    hidden_reported: int  # trunks reported hidden at the diameter height (no diameter)
    pairs: tuple[TrunkPair, ...] = field(default_factory=tuple)


@dataclass(frozen=True)
class GroundErrors:
    n: int
    reference: str  # "seen": the plane of the ground the side saw; "full": the 0.5 m disk around the trunk
    normal_error_deg_median: float | None
    normal_error_deg_max: float | None
    height_error_mm_median: float | None  # absolute, at the tree along the true normal
    height_error_mm_max: float | None
    normal_error_full_deg_median: float | None  # against the full-disk plane, for reference
    height_error_full_mm_median: float | None
    per_tree: tuple[tuple[int, float, float], ...] = ()  # (trunk id, normal error deg, signed height error mm)


def local_alignment(stamps: np.ndarray, est: StampedTrajectory | None, true: StampedTrajectory,
                     T_world_odom: np.ndarray) -> np.ndarray:
    """(4, 4) world <- estimated odom near the median of `stamps` (the global T_world_odom without them)."""
    if est is None or not len(stamps) or not len(est.stamps):
        return T_world_odom
    s = float(np.median(stamps))
    i = int(np.argmin(np.abs(est.stamps - s)))
    j = int(np.argmin(np.abs(true.stamps - est.stamps[i])))
    T_est = pose_matrices(est.positions[i:i + 1], est.quaternions[i:i + 1])[0]
    T_true = pose_matrices(true.positions[j:j + 1], true.quaternions[j:j + 1])[0]
    return T_world_odom @ T_true @ np.linalg.inv(T_est)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b)), -1, 1))))


def _stats(v: list[float]) -> tuple[float | None, float | None]:
    return (float(np.mean(np.abs(v))), float(np.mean(v))) if v else (None, None)


def trunk_errors(gt: GroundTruth, side: str, trunks: list[ResultTrunk], est: StampedTrajectory | None
                 ) -> tuple[TrunkErrors, dict[int, tuple[TrueTree, np.ndarray]]]:
    """Metrics of one side's trunks; also trunk id -> (its true tree, world <- odom alignment) for grounds."""
    ts = gt.sides[side]
    mine = [t for t in trunks if t.side == side]
    in_view = [t for t in gt.trees if t.trunk_seen.get(side) is not False]
    pos = np.array([t.position[:2] for t in gt.trees]).reshape(-1, 2)
    pairs: list[TrunkPair] = []
    matched_true: set[int] = set()
    links: dict[int, tuple[TrueTree, np.ndarray]] = {}
    for r in mine:
        T = local_alignment(r.stamps, est, ts.trajectory, ts.T_world_odom)
        base_w = T[:3, :3] @ r.base + T[:3, 3]
        d = np.linalg.norm(pos - base_w[:2], axis=1) if len(pos) else np.zeros(0)
        if not len(d) or d.min() > TRUNK_MATCH_RADIUS_M:
            continue
        k = int(np.argmin(d))
        tree = gt.trees[k]
        if tree.id in matched_true:  # a second trunk on one tree: a false report
            continue
        matched_true.add(tree.id)
        links[r.id] = (tree, T)
        pairs.append(TrunkPair(
            true_id=tree.id, trunk_id=r.id, distance_m=float(d[k]), diameter_true_mm=1000 * tree.diameter_m,
            diameter_mm=None if r.diameter_m is None else 1000 * r.diameter_m,
            diameter_3d_only_mm=None if r.diameter_3d_only_m is None else 1000 * r.diameter_3d_only_m,
            axis_error_deg=_angle_deg(T[:3, :3] @ r.axis, tree.trunk_axis), flags=r.flags))
    in_view_ids = {t.id for t in in_view}
    err = [p.diameter_mm - p.diameter_true_mm for p in pairs if p.diameter_mm is not None]
    err3 = [p.diameter_3d_only_mm - p.diameter_true_mm for p in pairs if p.diameter_3d_only_mm is not None]
    mae, bias = _stats(err)
    mae3, bias3 = _stats(err3)
    return TrunkErrors(
        true_in_view=len(in_view), reported=len(mine), matched=len(pairs),
        recall=len(matched_true & in_view_ids) / len(in_view) if in_view else None,
        precision=len(pairs) / len(mine) if mine else None,
        diameter_n=len(err), diameter_mae_mm=mae, diameter_bias_mm=bias,
        diameter_3d_only_mae_mm=mae3, diameter_3d_only_bias_mm=bias3,
        axis_error_deg=float(np.median([p.axis_error_deg for p in pairs])) if pairs else None,
        hidden_reported=sum("hidden_at_diameter_height" in r.flags for r in mine),
        pairs=tuple(pairs),
    ), links


def plane_errors(n_w: np.ndarray, q_w: np.ndarray, p_t: np.ndarray, n_t: np.ndarray) -> tuple[float, float]:
    """(normal error deg, signed height mm of our plane above the true one at p_t, along n_t)."""
    denom = float(n_w @ n_t)
    s = -float(n_w @ (p_t - q_w)) / denom if abs(denom) > 1e-6 else float("inf")
    return _angle_deg(n_w, n_t), 1000.0 * s


def ground_errors(side: str, grounds: list[ResultGround],
                  links: dict[int, tuple[TrueTree, np.ndarray]]) -> GroundErrors:
    seen_e, full_e, ids = [], [], []
    refs = set()
    for g in grounds:
        if g.side != side or g.trunk_id not in links:
            continue
        tree, T = links[g.trunk_id]
        n_w, q_w = T[:3, :3] @ g.normal, T[:3, :3] @ g.point + T[:3, 3]
        seen = tree.seen_ground.get(side)
        ref = seen if seen is not None else (tree.ground_point, tree.ground_normal)
        refs.add("seen" if seen is not None else "full")
        seen_e.append(plane_errors(n_w, q_w, ref[0], ref[1]))
        ids.append(g.trunk_id)
        full_e.append(plane_errors(n_w, q_w, tree.ground_point, tree.ground_normal))
    if not seen_e:
        return GroundErrors(0, "", None, None, None, None, None, None)
    a = np.array(seen_e)
    f = np.array(full_e)
    return GroundErrors(
        n=len(a), reference="seen" if refs == {"seen"} else ("full" if refs == {"full"} else "mixed"),
        normal_error_deg_median=float(np.median(a[:, 0])), normal_error_deg_max=float(a[:, 0].max()),
        height_error_mm_median=float(np.median(np.abs(a[:, 1]))), height_error_mm_max=float(np.abs(a[:, 1]).max()),
        normal_error_full_deg_median=float(np.median(f[:, 0])),
        height_error_full_mm_median=float(np.median(np.abs(f[:, 1]))),
        per_tree=tuple((i, float(e[0]), float(e[1])) for i, e in zip(ids, a, strict=True)),
    )
