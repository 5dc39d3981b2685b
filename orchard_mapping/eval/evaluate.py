"""`evaluate_result`: compare one result folder with the simulator's ground truth.

Reads only the contract files (docs/results.md); a part the run did not
produce is reported as skipped, never an error. A part that is present but
malformed raises ResultFormatError.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from orchard_mapping.core.geometry import move_with_keyframes, pose_matrices, transform_points
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.errors import AlignmentError, ResultFormatError
from orchard_mapping.eval.ground_truth import GroundTruth, load_ground_truth
from orchard_mapping.eval.landmarks import ground_errors, trunk_errors
from orchard_mapping.eval.metrics import (
    DoubleCount,
    MergeError,
    TrajectoryError,
    double_count,
    map_merge_error,
    match_trees,
    merge_error,
    rigid_rmse_mm,
    trajectory_between,
    trajectory_error,
)
from orchard_mapping.eval.report import (
    EvaluationReport,
    FruitCountError,
    MatchingSummary,
    TimingSummary,
    TraitErrors,
    TreePair,
)
from orchard_mapping.eval.segmentation import (
    TREE_SURFACES_NPZ,
    SegmentationScore,
    load_tree_surfaces,
    segmentation_score,
)
from orchard_mapping.io.landmarks import GROUNDS_JSON, TRUNKS_JSON, read_grounds, read_trunks
from orchard_mapping.io.laz import TREES_LAZ, read_laz
from orchard_mapping.io.results import (
    SIDE_MERGE_JSON,
    TIMINGS_JSON,
    TREES_CSV,
    TREES_JSON,
    ResultTree,
    map_trajectory_filename,
    read_side_merge,
    read_timings,
    read_trees,
    read_trees_csv,
    read_tum,
    trajectory_filename,
)

__all__ = ["evaluate_result", "trunk_scene_points"]


CONFIG_EFFECTIVE = "config.effective.yaml"
DEFAULT_DIAMETER_HEIGHT_M = 0.30  # m, where trunk diameters are stated when the truth does not say


def _keyframe_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (K,), poses (K, 4, 4)) of a TUM file."""
    tr = read_tum(path)
    return np.asarray(tr.stamps, float), pose_matrices(tr.positions, tr.quaternions)


def _trunk_axis_gaps_mm(result_dir: Path, sm, trunks, height_m: float) -> dict[str, float] | None:
    """Median and max distance (mm) between the two sides' axes of each paired trunk at the diameter
    height, after the merge: each side's trunk axis (trunks.json, its own frame; the cone's where fitted)
    carried into map as its keyframes were (trajectory_<side>.tum -> trajectory_<side>_map.tum). None if a
    part is missing."""
    pairs = (sm.residuals or {}).get("pairs") or []
    frames = {}
    for side in ("front", "back"):
        own, in_map = result_dir / trajectory_filename(side), result_dir / map_trajectory_filename(side)
        if not (own.is_file() and in_map.is_file()):
            return None
        (s0, P0), (s1, P1) = _keyframe_poses(own), _keyframe_poses(in_map)
        if len(s0) != len(s1) or not np.allclose(s0, s1, atol=1e-6):
            raise ResultFormatError(f"{in_map.name}: its keyframes are not those of {own.name}")
        frames[side] = (P0, P1)
    by = {(t.side, t.id): t for t in trunks}
    gaps = []
    for p in pairs:
        ends = []
        for side, key in (("front", "front_id"), ("back", "back_id")):
            t = by.get((side, int(p[key])))
            if t is None:
                raise ResultFormatError(f"side_merge.json pairs {side} trunk {p[key]}, absent from {TRUNKS_JSON}")
            a = t.axis if t.axis_cone is None else t.axis_cone  # the cone's: the trunk's centreline
            a = a / np.linalg.norm(a)
            p0 = t.base + height_m * a  # the axis at the diameter height
            pts = np.array([p0, p0 + a])  # (2, 3) on the axis
            ends.append(move_with_keyframes(pts, *frames[side]))
        (f0, f1), (b0, b1) = ends
        a = (b1 - b0) / np.linalg.norm(b1 - b0)
        d = f0 - b0
        gaps.append(1000.0 * float(np.linalg.norm(d - (d @ a) * a)))
    if not gaps:
        return None
    return {"median": float(np.median(gaps)), "max": float(np.max(gaps)), "n": len(gaps)}


def _map_error_trunk_sweep(gt: GroundTruth, maps: dict[str, StampedTrajectory], trunks: list,
                           world_bases: np.ndarray, max_dt_s: float, skipped: dict[str, str]) -> MergeError | None:
    """The merged map's error with each side's keyframes limited to the stretch of time in which it saw its
    trunks (its first to its last trunk observation in trunks.json): on a two-sweep path the raised sweep
    sees no trunk, and its own drift against the level sweep is a single-side error, not the merge's."""
    spans = {}
    for side in ("front", "back"):
        stamps = np.concatenate([t.stamps for t in trunks if t.side == side] or [np.zeros(0)])
        if stamps.size == 0:
            skipped["merge.map_trunk_sweep"] = f"the {side} side has no trunk observation in {TRUNKS_JSON}"
            return None
        spans[side] = (float(stamps.min()) - max_dt_s, float(stamps.max()) + max_dt_s)
    est = {side: trajectory_between(maps[side], *spans[side]) for side in ("front", "back")}
    try:
        return map_merge_error(est["front"], est["back"], gt.sides["front"].trajectory, gt.sides["back"].trajectory,
                               gt.sides["front"].T_world_odom, gt.sides["back"].T_world_odom, world_bases, max_dt_s,
                               scene_points=trunk_scene_points(gt))
    except AlignmentError as err:
        skipped["merge.map_trunk_sweep"] = str(err)
        return None


def trunk_scene_points(gt: GroundTruth) -> np.ndarray:
    """(2T, 3) world: the true trunk bases and tops, what the merged map's error fits each side on."""
    return np.array([p for t in gt.trees for p in (t.trunk_base, t.trunk_top)], float).reshape(-1, 3)


def _rgb_only(result_dir: Path) -> bool:
    """True if the run's effective configuration says `input.mode: rgb` (trajectories up to scale)."""
    path = result_dir / CONFIG_EFFECTIVE
    if not path.is_file():
        return False
    try:
        cfg = yaml.safe_load(path.read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError) as err:
        raise ResultFormatError(f"{path}: not readable YAML: {err}") from err
    mode = cfg.get("input", {}).get("mode") if isinstance(cfg, dict) and isinstance(cfg.get("input"), dict) else None
    return mode == "rgb"


def _mean_or_none(v: np.ndarray) -> float | None:
    return float(v.mean()) if v.size else None


INTERVAL_TRAITS = {"trunk_diameter_m": "diameter_m", "height_m": "height_m", "canopy_volume_m3": "canopy_volume_m3"}


def _interval_coverage(gt: GroundTruth, trees: list[ResultTree], m) -> dict[str, dict[str, float]]:
    """Per trait: how many matched trees give a 90 % interval (trees.json `interval_90`) and the share of
    them whose true value lies inside it (a calibrated interval holds it 85-95 % of the time)."""
    hits: dict[str, list[bool]] = {}
    for i, j in zip(m.true_index.tolist(), m.est_index.tolist(), strict=True):
        intervals = trees[j].extra.get("interval_90") or {}
        for trait, true_attr in INTERVAL_TRAITS.items():
            lo_hi = intervals.get(trait)
            true = getattr(gt.trees[i], true_attr)
            if lo_hi is not None and not (trait == "canopy_volume_m3" and not true > 0):  # 0: no volume truth
                hits.setdefault(trait, []).append(bool(lo_hi[0] <= true <= lo_hi[1]))
    return {trait: {"n": len(h), "coverage": float(np.mean(h))} for trait, h in hits.items()}


def _trees_part(
    gt: GroundTruth, trees: list[ResultTree], T_front_world: np.ndarray, radius_m: float, gate_factor: float
) -> tuple[MatchingSummary, tuple[TreePair, ...], TraitErrors, FruitCountError, DoubleCount | None]:
    true_xyz = transform_points(T_front_world, np.array([t.position for t in gt.trees]).reshape(-1, 3))  # (T, 3)
    est_xyz = np.array([t.position for t in trees], dtype=float).reshape(-1, 3)  # (E, 3)
    m = match_trees(true_xyz, est_xyz, radius_m)
    pairs = tuple(
        TreePair(
            true_id=gt.trees[i].id,
            result_id=trees[j].id,
            distance_m=float(d),
            true_trunk_diameter_m=gt.trees[i].diameter_m,
            est_trunk_diameter_m=trees[j].trunk_diameter_m,
            true_height_m=gt.trees[i].height_m,
            est_height_m=trees[j].height_m,
            true_canopy_volume_m3=gt.trees[i].canopy_volume_m3,
            est_canopy_volume_m3=trees[j].canopy_volume_m3,
            true_fruit_visible=gt.trees[i].fruit_visible["either"],
            true_fruit_all=gt.trees[i].fruit_count,
            est_fruit_count=trees[j].fruit_count,
        )
        for i, j, d in zip(m.true_index.tolist(), m.est_index.tolist(), m.distance_m.tolist(), strict=True)
    )
    summary = MatchingSummary(
        true_trees=len(gt.trees),
        result_trees=len(trees),
        matched=len(pairs),
        missed=int(m.missed.size),
        false=int(m.false.size),
        mean_distance_m=_mean_or_none(m.distance_m),
        missed_ids=tuple(gt.trees[i].id for i in m.missed.tolist()),
        false_ids=tuple(trees[j].id for j in m.false.tolist()),
        position_rmse_mm=rigid_rmse_mm(est_xyz[m.est_index], true_xyz[m.true_index]),
    )

    def diffs(true_attr: str, est_attr: str) -> tuple[np.ndarray, np.ndarray]:
        sel = [p for p in pairs if getattr(p, est_attr) is not None]
        return (
            np.array([getattr(p, est_attr) for p in sel], dtype=float),
            np.array([getattr(p, true_attr) for p in sel], dtype=float),
        )

    d_est, d_true = diffs("true_trunk_diameter_m", "est_trunk_diameter_m")
    h_est, h_true = diffs("true_height_m", "est_height_m")
    v_est, v_true = diffs("true_canopy_volume_m3", "est_canopy_volume_m3")
    v_ok = v_true > 0.0  # a percentage of a zero volume is undefined
    v_rel = (v_est[v_ok] - v_true[v_ok]) / v_true[v_ok]
    mae_d, mae_h = _mean_or_none(np.abs(d_est - d_true)), _mean_or_none(np.abs(h_est - h_true))
    mape, bias = _mean_or_none(np.abs(v_rel)), _mean_or_none(v_rel)
    traits = TraitErrors(
        trunk_diameter_mae_mm=None if mae_d is None else 1000.0 * mae_d,
        trunk_diameter_n=int(d_est.size),
        height_mae_cm=None if mae_h is None else 100.0 * mae_h,
        height_n=int(h_est.size),
        canopy_volume_mape_percent=None if mape is None else 100.0 * mape,
        canopy_volume_bias_percent=None if bias is None else 100.0 * bias,
        canopy_volume_n=int(v_rel.size),
        interval_coverage=_interval_coverage(gt, trees, m),
    )

    counted = [p for p in pairs if p.est_fruit_count is not None]
    est = sum(p.est_fruit_count for p in counted)  # type: ignore[misc]
    vis = sum(p.true_fruit_visible for p in counted)
    tot = sum(p.true_fruit_all for p in counted)
    fruit = FruitCountError(
        n_trees=len(counted),
        estimated=est,
        true_visible=vis,
        true_all=tot,
        error_visible_percent=100.0 * (est - vis) / vis if vis else None,
        error_all_percent=100.0 * (est - tot) / tot if tot else None,
    )

    dc = None
    if any(t.fruit_positions is not None for t in trees):
        est_f = np.concatenate([np.zeros((0, 3))] + [t.fruit_positions for t in trees if t.fruit_positions is not None])
        true_f = transform_points(
            T_front_world, np.concatenate([np.zeros((0, 3))] + [t.fruit_positions for t in gt.trees])
        )
        radii = np.concatenate([np.zeros(0)] + [t.fruit_radii for t in gt.trees])
        dia = np.concatenate([np.zeros(0)] + [_fruit_diameters(t) for t in trees if t.fruit_positions is not None])
        both = sum(int(t.fruit_visible.get("both", 0)) for t in gt.trees)
        dc = double_count(est_f, true_f, radii, gate_factor, est_diameter_m=dia, true_seen_from_both=both)
    return summary, pairs, traits, fruit, dc


def _timings_part(gt: GroundTruth, result_dir: Path) -> TimingSummary:
    tm = read_timings(result_dir / TIMINGS_JSON)
    rec, source = tm.recording_duration_s, "timings.json"
    if rec is None or rec <= 0.0:
        rec = sum(s.duration_s for s in gt.sides.values())
        source = "ground truth"
        if rec <= 0.0:
            rec, source = None, "unknown"
    return TimingSummary(
        stages=dict(tm.stages),
        total_s=tm.total_s,
        frames=tm.frames,
        recording_duration_s=rec,
        recording_duration_source=source,
        realtime_factor=tm.elapsed_s / rec if rec else None,
        elapsed_s=tm.elapsed_s,
    )


def _fruit_diameters(t: ResultTree) -> np.ndarray:
    """(F,) m, the diameters trees.json gives beside a tree's fruit_positions (fruit_diameters_m), NaN where it
    gives none or not one per fruit."""
    n = len(t.fruit_positions)
    dia = np.asarray(t.extra.get("fruit_diameters_m", []), float).reshape(-1)
    return dia if len(dia) == n else np.full(n, np.nan)


def _segmentation_part(truth_dir: Path, result_dir: Path, pairs: tuple[TreePair, ...], T_front_world: np.ndarray,
                       skipped: dict[str, str]) -> SegmentationScore | None:
    surfaces, laz = truth_dir / TREE_SURFACES_NPZ, result_dir / TREES_LAZ
    for path in (surfaces, laz):
        if not path.is_file():
            skipped["segmentation"] = f"{path.name} absent"
            return None
    if not pairs:
        skipped["segmentation"] = "no matched tree"
        return None
    pts, tree = load_tree_surfaces(surfaces)
    cloud = read_laz(laz)
    return segmentation_score(cloud["points"], cloud["tree_id"], pts, tree, T_front_world,
                              {p.true_id: p.result_id for p in pairs})


def evaluate_result(
    truth_path: str | Path | GroundTruth,
    result_dir: str | Path,
    match_radius_m: float = 0.3,
    *,
    trajectory_max_dt_s: float = 0.005,
    fruit_gate_factor: float = 1.5,
    scale_alignment: bool | None = None,
) -> EvaluationReport:
    """Evaluate `result_dir` against `truth_path` (ground_truth.json, or its GroundTruth already loaded: files
    beside it, tree_surfaces.npz, are looked for beside GroundTruth.path).

    match_radius_m: largest 3D distance (m, map) of a matched tree pair.
    trajectory_max_dt_s: stamp association tolerance (s).
    fruit_gate_factor: an estimated fruit matches a true fruit within this x its radius.
    scale_alignment: fit scale in the ATE alignment; None = only if the run's
    config.effective.yaml says `input.mode: rgb`.
    Raises GroundTruthError / ResultFormatError for unusable inputs.
    """
    gt = truth_path if isinstance(truth_path, GroundTruth) else load_ground_truth(truth_path)
    result_dir = Path(result_dir)
    if not result_dir.is_dir():
        raise ResultFormatError(f"{result_dir}: result folder not found")
    skipped: dict[str, str] = {}
    T_front_world = np.linalg.inv(gt.sides["front"].T_world_odom)  # world -> odom_front (= map)

    matching = traits = fruit = None
    dc: DoubleCount | None = None
    pairs: tuple[TreePair, ...] = ()
    if (result_dir / TREES_JSON).is_file():
        trees = read_trees(result_dir / TREES_JSON)
    elif (result_dir / TREES_CSV).is_file():
        trees = read_trees_csv(result_dir / TREES_CSV)
    else:
        trees = None
        for part in ("matching", "traits", "fruit_count", "double_count"):
            skipped[part] = f"{TREES_JSON} absent"
    if trees is not None:
        matching, pairs, traits, fruit, dc = _trees_part(gt, trees, T_front_world, match_radius_m, fruit_gate_factor)
        if dc is None:
            skipped["double_count"] = "no result tree carries fruit_positions"
        if fruit.n_trees == 0:
            skipped["fruit_count"] = "no matched tree has a fruit_count"
            fruit = None

    merge: MergeError | None = None
    merge_map: MergeError | None = None
    merge_map_trunk_sweep: MergeError | None = None
    gaps: dict[str, float] | None = None
    trunks = read_trunks(result_dir / TRUNKS_JSON) if (result_dir / TRUNKS_JSON).is_file() else None
    if (result_dir / SIDE_MERGE_JSON).is_file():
        sm = read_side_merge(result_dir / SIDE_MERGE_JSON)
        T_back_world = np.linalg.inv(gt.sides["back"].T_world_odom)
        bases = transform_points(T_back_world, np.array([t.trunk_base for t in gt.trees]).reshape(-1, 3))
        try:
            merge = merge_error(sm.T_front_back, gt.T_front_back, bases)
        except AlignmentError as err:
            skipped["merge"] = str(err)
        maps = [result_dir / map_trajectory_filename(side) for side in ("front", "back")]
        if all(p.is_file() for p in maps) and not (_rgb_only(result_dir) if scale_alignment is None else scale_alignment):
            world_bases = np.array([t.trunk_base for t in gt.trees]).reshape(-1, 3)
            in_map = {side: read_tum(p) for side, p in zip(("front", "back"), maps, strict=True)}
            try:
                merge_map = map_merge_error(in_map["front"], in_map["back"], gt.sides["front"].trajectory,
                                            gt.sides["back"].trajectory, gt.sides["front"].T_world_odom,
                                            gt.sides["back"].T_world_odom, world_bases, trajectory_max_dt_s,
                                            scene_points=trunk_scene_points(gt))
            except AlignmentError as err:
                skipped["merge.map"] = str(err)
            if merge_map is not None and trunks is not None:
                merge_map_trunk_sweep = _map_error_trunk_sweep(gt, in_map, trunks, world_bases, trajectory_max_dt_s,
                                                               skipped)
        else:
            skipped["merge.map"] = "no metric trajectory_<side>_map.tum pair"
        if trunks is not None:
            gaps = _trunk_axis_gaps_mm(result_dir, sm, trunks,
                                       gt.diameter_height_m or DEFAULT_DIAMETER_HEIGHT_M)
    else:
        skipped["merge"] = f"{SIDE_MERGE_JSON} absent"

    with_scale = _rgb_only(result_dir) if scale_alignment is None else scale_alignment
    sides: dict[str, TrajectoryError | None] = {}
    for name, side in gt.sides.items():
        path = result_dir / trajectory_filename(name)
        if not path.is_file():
            sides[name] = None
            skipped[f"sides.{name}"] = f"{path.name} absent"
            continue
        te = trajectory_error(read_tum(path, side.frame), side.trajectory, trajectory_max_dt_s, with_scale)
        sides[name] = te
        if te.drift_percent is None:
            skipped[f"sides.{name}"] = f"{te.n_associated} poses associated within {trajectory_max_dt_s * 1000:g} ms"

    trunks_e: dict[str, object] = {}
    grounds_e: dict[str, object] = {}
    if trunks is not None:
        grounds = read_grounds(result_dir / GROUNDS_JSON) if (result_dir / GROUNDS_JSON).is_file() else []
        for name, side in gt.sides.items():
            path = result_dir / trajectory_filename(name)
            est = read_tum(path, side.frame) if path.is_file() else None
            te, links = trunk_errors(gt, name, trunks, est)
            trunks_e[name] = te
            grounds_e[name] = ground_errors(name, grounds, links)
    else:
        skipped["trunks"] = f"{TRUNKS_JSON} absent"

    segmentation = _segmentation_part(Path(gt.path).parent, result_dir, pairs, T_front_world, skipped)

    timings = None
    if (result_dir / TIMINGS_JSON).is_file():
        timings = _timings_part(gt, result_dir)
    else:
        skipped["timings"] = f"{TIMINGS_JSON} absent"

    return EvaluationReport(
        truth_path=Path(gt.path),
        result_dir=result_dir,
        match_radius_m=float(match_radius_m),
        matching=matching,
        traits=traits,
        fruit_count=fruit,
        double_count=dc,
        merge=merge,
        merge_map=merge_map,
        merge_map_trunk_sweep=merge_map_trunk_sweep,
        sides=sides,
        timings=timings,
        pairs=pairs,
        skipped=skipped,
        trunks=trunks_e,
        grounds=grounds_e,
        trunk_axis_gap_mm=gaps,
        segmentation=segmentation,
    )
