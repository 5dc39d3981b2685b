"""evaluate_result on a result folder derived from the synthetic truth: exact, then perturbed."""

from __future__ import annotations

import dataclasses
import json
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rich.console import Console
from scipy.spatial.transform import Rotation

from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.errors import GroundTruthError, ResultFormatError
from orchard_mapping.eval import EvaluationReport, evaluate_result
from orchard_mapping.eval.metrics import trajectory_error
from orchard_mapping.io.results import ResultTree, read_side_merge, read_trees, write_side_merge, write_trees, write_tum


def _edit_trees(result_dir: Path, edit: Callable[[list[ResultTree]], list[ResultTree]]) -> None:
    write_trees(result_dir, edit(read_trees(result_dir)))


def _render(table: Any) -> str:
    console = Console(record=True, width=220)
    console.print(table)
    return console.export_text()


def _true_path_length(truth: dict[str, Any], side: str) -> float:
    p = np.asarray(truth["sides"][side]["trajectory"])[:, 1:4]
    return float(np.sum(np.sqrt(np.sum(np.diff(p, axis=0) ** 2, axis=1))))


def test_exact_result_scores_zero(truth_path: Path, result_dir: Path) -> None:
    rep = evaluate_result(truth_path, result_dir)
    assert rep.matching is not None and (rep.matching.matched, rep.matching.missed, rep.matching.false) == (3, 0, 0)
    assert rep.matching.mean_distance_m == pytest.approx(0.0, abs=1e-9)
    assert rep.traits is not None
    assert rep.traits.trunk_diameter_mae_mm == pytest.approx(0.0, abs=1e-9)
    assert rep.traits.height_mae_cm == pytest.approx(0.0, abs=1e-9)
    assert rep.traits.canopy_volume_mape_percent == pytest.approx(0.0, abs=1e-9)
    assert rep.fruit_count is not None
    assert (rep.fruit_count.estimated, rep.fruit_count.true_visible, rep.fruit_count.true_all) == (9, 9, 12)
    assert rep.fruit_count.error_visible_percent == pytest.approx(0.0)
    assert rep.fruit_count.error_all_percent == pytest.approx(-25.0)
    assert rep.double_count is not None and rep.double_count.rate_percent == 0.0 and rep.double_count.false == 0
    assert rep.merge is not None
    assert rep.merge.rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    assert rep.merge.translation_error_mm == pytest.approx(0.0, abs=1e-6)
    assert rep.merge.scale_error_percent is None
    assert rep.merge_map is not None and rep.merge_map.rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    assert rep.merge_map.translation_error_mm == pytest.approx(0.0, abs=1e-6)
    for side in ("front", "back"):
        e = rep.sides[side]
        assert e is not None and e.n_associated == 11 and e.alignment == "se3"
        assert e.drift_percent == pytest.approx(0.0, abs=1e-9)
        assert e.ate_percent == pytest.approx(0.0, abs=1e-9)
    assert rep.timings is not None and rep.timings.total_s == pytest.approx(4.0)
    assert rep.timings.realtime_factor == pytest.approx(1.0)
    # trunks and grounds: test_eval_landmarks.py; per-point segmentation: test_eval_segmentation.py
    assert rep.skipped == {"trunks": "trunks.json absent", "segmentation": "tree_surfaces.npz absent"}
    assert len(rep.pairs) == 3 and {(p.true_id, p.result_id) for p in rep.pairs} == {(0, 10), (1, 11), (2, 12)}


def test_to_dict_is_json_with_stable_keys(truth_path: Path, result_dir: Path, tmp_path: Path) -> None:
    full = evaluate_result(truth_path, result_dir).to_dict()
    empty_dir = tmp_path / "empty"
    empty_dir.mkdir()
    empty = evaluate_result(truth_path, empty_dir).to_dict()
    assert list(full) == list(empty)
    assert json.loads(json.dumps(full)) == full
    assert set(full["sides"]) == {"front", "back"}
    assert set(full["sides"]["front"]) >= {"drift_percent", "ate_percent", "ate_mm", "n_associated"}
    assert full["traits"]["trunk_diameter_mae_mm"] == pytest.approx(0.0, abs=1e-9)
    assert empty["sides"] == {"front": None, "back": None} and empty["matching"] is None
    assert set(empty["skipped"]) == {
        "matching",
        "traits",
        "fruit_count",
        "double_count",
        "merge",
        "sides.front",
        "sides.back",
        "trunks",
        "timings",
        "segmentation",
    }


def test_tables_render(truth_path: Path, result_dir: Path, tmp_path: Path) -> None:
    rep = evaluate_result(truth_path, result_dir)
    text = _render(rep.table())
    for name in (
        "trunk diameter MAE",
        "height MAE",
        "canopy volume error",
        "double-count rate",
        "merge rotation error",
        "front drift",
        "back ATE",
        "real-time factor",
    ):
        assert name in text
    assert "metric" in text and "unit" in text and "note" in text
    per_tree = _render(rep.per_tree_table())
    assert "65.0 / 65.0" in per_tree  # tree 1 diameter in mm
    empty_dir = tmp_path / "nothing"
    empty_dir.mkdir()
    assert "n/a" in _render(evaluate_result(truth_path, empty_dir).table())


def test_trait_errors(truth_path: Path, result_dir: Path) -> None:
    def perturb(trees: list[ResultTree]) -> list[ResultTree]:
        out = [
            dataclasses.replace(
                t,
                trunk_diameter_m=t.trunk_diameter_m + 0.005,
                height_m=t.height_m + 0.10,
                canopy_volume_m3=1.2 * t.canopy_volume_m3,
            )
            for t in trees
        ]
        out[2] = dataclasses.replace(out[2], height_m=None)
        return out

    _edit_trees(result_dir, perturb)
    t = evaluate_result(truth_path, result_dir).traits
    assert t is not None
    assert t.trunk_diameter_mae_mm == pytest.approx(5.0, abs=1e-9) and t.trunk_diameter_n == 3
    assert t.height_mae_cm == pytest.approx(10.0, abs=1e-9) and t.height_n == 2
    assert t.canopy_volume_mape_percent == pytest.approx(20.0)
    assert t.canopy_volume_bias_percent == pytest.approx(20.0)


def test_interval_coverage(truth_path: Path, result_dir: Path) -> None:
    """The share of matched trees whose 90 % interval (trees.json `interval_90`) holds the true value."""
    def with_intervals(trees: list[ResultTree]) -> list[ResultTree]:
        out = []
        for k, t in enumerate(trees):
            off = 0.0 if k else 0.5  # tree 0's height interval misses the truth by half a metre
            iv = {"height_m": [t.height_m - 0.01 + off, t.height_m + 0.01 + off],
                  "canopy_volume_m3": [0.9 * t.canopy_volume_m3, 1.1 * t.canopy_volume_m3]}
            out.append(dataclasses.replace(t, extra={**t.extra, "interval_90": iv}))
        return out

    _edit_trees(result_dir, with_intervals)
    cov = evaluate_result(truth_path, result_dir).traits.interval_coverage
    n = len(cov["height_m"]) and cov["height_m"]["n"]
    assert n == 3 and cov["height_m"]["coverage"] == pytest.approx(2 / 3)
    assert cov["canopy_volume_m3"] == {"n": 3, "coverage": 1.0}
    assert "trunk_diameter_m" not in cov  # no tree gives that interval


def test_fruit_count_error(truth_path: Path, result_dir: Path) -> None:
    _edit_trees(
        result_dir,
        lambda ts: [dataclasses.replace(ts[0], fruit_count=5), ts[1], dataclasses.replace(ts[2], fruit_count=None)],
    )
    f = evaluate_result(truth_path, result_dir).fruit_count
    assert f is not None and f.n_trees == 2
    assert (f.estimated, f.true_visible, f.true_all) == (8, 5, 7)
    assert f.error_visible_percent == pytest.approx(60.0)
    assert f.error_all_percent == pytest.approx(100.0 * (8 - 7) / 7)


def test_duplicated_fruit_is_a_double_count(truth_path: Path, result_dir: Path) -> None:
    def dup(trees: list[ResultTree]) -> list[ResultTree]:
        f = trees[0].fruit_positions
        assert f is not None
        return [dataclasses.replace(trees[0], fruit_positions=np.vstack([f, f[:1] + 0.01])), *trees[1:]]

    _edit_trees(result_dir, dup)
    d = evaluate_result(truth_path, result_dir).double_count
    assert d is not None
    assert (d.estimated, d.duplicates, d.unique_true, d.false) == (10, 1, 9, 0)
    assert d.rate_percent == pytest.approx(10.0)


def test_fruit_outside_the_gate_is_false_not_duplicate(truth_path: Path, result_dir: Path) -> None:
    def far(trees: list[ResultTree]) -> list[ResultTree]:
        f = trees[0].fruit_positions
        assert f is not None
        return [dataclasses.replace(trees[0], fruit_positions=np.vstack([f, f[:1] + [0.07, 0.0, 0.0]])), *trees[1:]]

    _edit_trees(result_dir, far)  # 7 cm > 1.5 x 4 cm
    d = evaluate_result(truth_path, result_dir).double_count
    assert d is not None and (d.duplicates, d.false) == (0, 1) and d.rate_percent == 0.0


def test_missing_extra_and_far_trees(truth_path: Path, result_dir: Path) -> None:
    original = read_trees(result_dir)
    write_trees(result_dir, original[1:])
    m = evaluate_result(truth_path, result_dir).matching
    assert m is not None and (m.matched, m.missed, m.false, m.missed_ids) == (2, 1, 0, (0,))

    extra = dataclasses.replace(original[0], id=99, position=(30.0, 0.0, 0.0))
    write_trees(result_dir, [*original, extra])
    m = evaluate_result(truth_path, result_dir).matching
    assert m is not None and (m.matched, m.missed, m.false, m.false_ids) == (3, 0, 1, (99,))

    p = np.array(original[2].position)
    moved = dataclasses.replace(original[2], position=tuple(p + [0.35, 0.0, 0.0]))
    write_trees(result_dir, [*original[:2], moved])
    rep = evaluate_result(truth_path, result_dir, match_radius_m=0.3)
    assert rep.matching is not None and (rep.matching.matched, rep.matching.missed, rep.matching.false) == (2, 1, 1)
    rep = evaluate_result(truth_path, result_dir, match_radius_m=0.4)
    assert rep.matching is not None and rep.matching.matched == 3
    assert max(pr.distance_m for pr in rep.pairs) == pytest.approx(0.35)


def test_tree_position_rmse_ignores_the_placement_but_not_the_shape(truth_path: Path, result_dir: Path) -> None:
    original = read_trees(result_dir)
    assert evaluate_result(truth_path, result_dir).matching.position_rmse_mm == pytest.approx(0.0, abs=1e-6)
    R = Rotation.from_rotvec([0.0, 0.0, 0.05]).as_matrix()  # the whole map turned and shifted: same shape
    moved = [dataclasses.replace(t, position=tuple(R @ np.array(t.position) + [0.05, -0.03, 0.02])) for t in original]
    write_trees(result_dir, moved)
    rep = evaluate_result(truth_path, result_dir)
    assert rep.matching.matched == 3 and rep.matching.position_rmse_mm == pytest.approx(0.0, abs=1e-6)
    assert rep.matching.mean_distance_m > 0.03
    bent = [*original[:2], dataclasses.replace(original[2], position=tuple(np.array(original[2].position)
                                                                           + [0.0, 0.0, 0.06]))]
    write_trees(result_dir, bent)  # one tree 6 cm up: the shape changes
    rmse = evaluate_result(truth_path, result_dir).matching.position_rmse_mm
    assert 10.0 < rmse < 60.0
    write_trees(result_dir, original[:2])
    assert evaluate_result(truth_path, result_dir).matching.position_rmse_mm is None  # two trees: no shape


def test_merge_errors(truth_path: Path, result_dir: Path, truth: dict[str, Any]) -> None:
    T_true = np.asarray(truth["T_front_back"])
    path = result_dir / "side_merge.json"
    dR = np.eye(4)
    dR[:3, :3] = Rotation.from_rotvec(np.radians(2.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    write_side_merge(path, T_true @ dR)
    g = evaluate_result(truth_path, result_dir).merge
    assert g is not None and g.rotation_error_deg == pytest.approx(2.0, abs=1e-9) and g.translation_error_mm > 1.0

    T = T_true.copy()
    T[:3, 3] += [0.010, 0.0, 0.0]
    write_side_merge(path, T)
    g = evaluate_result(truth_path, result_dir).merge
    assert (
        g is not None
        and g.translation_error_mm == pytest.approx(10.0)
        and g.rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    )

    T = T_true.copy()
    T[:3, :3] *= 1.02
    write_side_merge(path, T)
    g = evaluate_result(truth_path, result_dir).merge
    assert g is not None and read_side_merge(result_dir).scale == pytest.approx(1.02)
    assert g.scale_error_percent == pytest.approx(2.0) and g.rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    assert "merge scale error" in _render(evaluate_result(truth_path, result_dir).table())


def _write_traj(result_dir: Path, side: str, stamps: Any, pos: Any, quat: Any) -> None:
    write_tum(
        result_dir / f"trajectory_{side}.tum", StampedTrajectory(np.asarray(stamps), np.asarray(pos), np.asarray(quat))
    )


def test_linear_drift_matches_the_planted_value(
    truth_path: Path, result_dir: Path, truth: dict[str, Any], kit: types.SimpleNamespace
) -> None:
    kf = kit.true_trajectory(truth, "front", kit.keyframe_step)
    d = np.array([0.03, -0.02, 0.01])
    ramp = np.linspace(0.0, 1.0, kf.stamps.size)[:, None]
    _write_traj(result_dir, "front", kf.stamps, kf.positions + ramp * d, kf.quaternions)
    rep = evaluate_result(truth_path, result_dir)
    e = rep.sides["front"]
    assert e is not None and e.path_length_m == pytest.approx(_true_path_length(truth, "front"))
    assert e.drift_mm == pytest.approx(1000.0 * np.linalg.norm(d))
    assert e.drift_percent == pytest.approx(100.0 * np.linalg.norm(d) / _true_path_length(truth, "front"))
    assert e.ate_percent is not None and 0.0 < e.ate_percent < e.drift_percent
    back = rep.sides["back"]
    assert back is not None and back.drift_percent == pytest.approx(0.0, abs=1e-9)


def test_rigidly_moved_positions_have_no_ate_but_drift(
    truth_path: Path, result_dir: Path, truth: dict[str, Any], kit: types.SimpleNamespace
) -> None:
    kf = kit.true_trajectory(truth, "back", kit.keyframe_step)
    Rz = Rotation.from_euler("z", 3.0, degrees=True).as_matrix()
    p0 = kf.positions[0]
    moved = (kf.positions - p0) @ Rz.T + p0 + [0.5, -0.2, 0.1]  # orientations left as they were
    _write_traj(result_dir, "back", kf.stamps, moved, kf.quaternions)
    e = evaluate_result(truth_path, result_dir).sides["back"]
    planted = np.linalg.norm((Rz - np.eye(3)) @ (kf.positions[-1] - p0))
    assert e is not None and e.ate_mm == pytest.approx(0.0, abs=1e-6)
    assert e.drift_mm == pytest.approx(1000.0 * planted) and e.drift_percent > 1.0


def test_whole_poses_moved_rigidly_score_zero(
    truth_path: Path, result_dir: Path, truth: dict[str, Any], kit: types.SimpleNamespace
) -> None:
    kf = kit.true_trajectory(truth, "front", kit.keyframe_step)
    G = Rotation.from_euler("xyz", [20, -10, 35], degrees=True)
    pos = G.apply(kf.positions) + [1.0, 2.0, -3.0]
    quat = (G * Rotation.from_quat(kf.quaternions)).as_quat()
    _write_traj(result_dir, "front", kf.stamps, pos, quat)
    e = evaluate_result(truth_path, result_dir).sides["front"]
    assert e is not None
    assert e.drift_percent == pytest.approx(0.0, abs=1e-9) and e.ate_percent == pytest.approx(0.0, abs=1e-9)
    assert e.final_rotation_error_deg == pytest.approx(0.0, abs=1e-6)


def test_scaled_trajectory_uses_sim3_for_rgb_runs(
    truth_path: Path, result_dir: Path, truth: dict[str, Any], kit: types.SimpleNamespace
) -> None:
    kf = kit.true_trajectory(truth, "front", kit.keyframe_step)
    _write_traj(result_dir, "front", kf.stamps, 0.5 * kf.positions, kf.quaternions)
    e = evaluate_result(truth_path, result_dir).sides["front"]
    assert e is not None and e.alignment == "se3" and e.ate_mm > 10.0
    (result_dir / "config.effective.yaml").write_text("input:\n  mode: rgb\n")
    e = evaluate_result(truth_path, result_dir).sides["front"]
    assert e is not None and e.alignment == "sim3" and e.alignment_scale == pytest.approx(2.0)
    assert e.ate_mm == pytest.approx(0.0, abs=1e-6)
    # the drift beyond the one global scale: none here (without the scale the end is half the path off)
    assert e.drift_mm == pytest.approx(0.0, abs=1e-6) and e.final_rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    e = evaluate_result(truth_path, result_dir, scale_alignment=False).sides["front"]
    assert e is not None and e.alignment == "se3"


def test_sim3_drift_is_what_is_left_beyond_one_scale():
    """A colour-only side in units of its first baseline (x 0.4), with its end bent 0.1 m sideways over a
    10 m path: the sim3 drift sees the bend (about 0.1 m), the rigid one reads the scale as ~6 m of drift."""
    t = np.linspace(0.0, 20.0, 201)
    true_p = np.stack([0.5 * t, np.zeros_like(t), np.zeros_like(t)], 1)  # (N, 3) m, 10 m straight
    q = np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1))
    bend = np.stack([np.zeros_like(t), 0.1 * (t / t[-1]) ** 2, np.zeros_like(t)], 1)  # 0.1 m at the end
    true = StampedTrajectory(t, true_p, q)
    est = StampedTrajectory(t, 0.4 * (true_p + bend), q)
    sim3 = trajectory_error(est, true, with_scale=True)
    assert sim3.alignment_scale == pytest.approx(2.5, rel=1e-3)
    assert 70.0 < sim3.drift_mm < 110.0, sim3
    se3 = trajectory_error(est, true)
    assert se3.drift_mm > 5000.0, se3


def test_stamp_association_tolerance(
    truth_path: Path, result_dir: Path, truth: dict[str, Any], kit: types.SimpleNamespace
) -> None:
    kf = kit.true_trajectory(truth, "front", kit.keyframe_step)
    _write_traj(result_dir, "front", kf.stamps + 0.004, kf.positions, kf.quaternions)
    e = evaluate_result(truth_path, result_dir).sides["front"]
    assert e is not None and e.n_associated == kf.stamps.size
    _write_traj(result_dir, "front", kf.stamps + 0.010, kf.positions, kf.quaternions)
    rep = evaluate_result(truth_path, result_dir)
    e = rep.sides["front"]
    assert e is not None and e.n_associated == 0 and e.drift_percent is None and e.ate_percent is None
    assert "sides.front" in rep.skipped
    assert json.dumps(rep.to_dict())


def test_partial_folder_and_timing_fallback(truth_path: Path, result_dir: Path) -> None:
    for name in ("side_merge.json", "trajectory_back.tum", "trees.json"):
        (result_dir / name).unlink()
    (result_dir / "timings.json").write_text(json.dumps({"stages": {"odometry": 2.0}}))
    rep = evaluate_result(truth_path, result_dir)
    assert isinstance(rep, EvaluationReport)
    assert rep.merge is None and rep.sides["back"] is None and rep.sides["front"] is not None
    # trees.csv still there: matching works, fruit positions (json only) do not
    assert rep.matching is not None and rep.matching.matched == 3 and rep.double_count is None
    assert set(rep.skipped) == {"merge", "sides.back", "double_count", "trunks", "segmentation"}
    assert rep.timings is not None and rep.timings.recording_duration_source == "ground truth"
    assert rep.timings.realtime_factor == pytest.approx(2.0 / (30 / 15.0 * 2))
    assert "n/a" in _render(rep.table())
    # stages that overlapped sum to more than the run took: the wall clock, when given, is what is divided
    (result_dir / "timings.json").write_text(json.dumps({"stages": {"odometry": 2.0, "trunks": 1.0}, "wall_s": 2.5}))
    tm = evaluate_result(truth_path, result_dir).timings
    assert tm is not None and tm.total_s == pytest.approx(3.0) and tm.elapsed_s == pytest.approx(2.5)
    assert tm.realtime_factor == pytest.approx(2.5 / (30 / 15.0 * 2))


def test_bad_inputs_raise_typed_errors(truth_path: Path, result_dir: Path, tmp_path: Path) -> None:
    with pytest.raises(ResultFormatError, match="result folder not found"):
        evaluate_result(truth_path, tmp_path / "missing")
    with pytest.raises(GroundTruthError, match="not found"):
        evaluate_result(tmp_path / "missing.json", result_dir)
    (result_dir / "trajectory_front.tum").write_text("0 0 0 0 0 0 0 1\nbroken line\n")
    with pytest.raises(ResultFormatError, match=r"trajectory_front\.tum:2"):
        evaluate_result(truth_path, result_dir)


def test_truth_without_trees_does_not_crash(tmp_path: Path, truth: dict[str, Any], result_dir: Path) -> None:
    truth["trees"], truth["n_trees"] = [], 0
    path = tmp_path / "gt_empty.json"
    path.write_text(json.dumps(truth))
    rep = evaluate_result(path, result_dir)
    assert rep.matching is not None and (rep.matching.matched, rep.matching.false) == (0, 3)
    assert rep.double_count is not None and rep.double_count.false == 9
    assert rep.merge is None and "merge" in rep.skipped
    assert json.dumps(rep.to_dict()) and _render(rep.table())


def _write_map_trajectories(result_dir: Path, truth: dict[str, Any], kit: types.SimpleNamespace,
                            move_back: np.ndarray, move_both: np.ndarray) -> None:
    """Both sides' true keyframes in map (= odom_front), the back side moved by move_back (4, 4) in map,
    then both by move_both (4, 4)."""
    T_fb = np.asarray(truth["T_front_back"])
    for side, T in (("front", move_both), ("back", move_both @ move_back @ T_fb)):
        kf = kit.true_trajectory(truth, side, kit.keyframe_step)
        P = np.repeat(np.eye(4)[None], kf.stamps.size, axis=0)
        P[:, :3, :3] = Rotation.from_quat(kf.quaternions).as_matrix()
        P[:, :3, 3] = kf.positions
        P = T @ P
        write_tum(result_dir / f"trajectory_{side}_map.tum",
                  StampedTrajectory(kf.stamps, P[:, :3, 3], Rotation.from_matrix(P[:, :3, :3]).as_quat()))


def test_merged_map_error_leaves_out_what_both_sides_share(
    truth_path: Path, result_dir: Path, truth: dict[str, Any], kit: types.SimpleNamespace
) -> None:
    """The merged map's error measures the back side against the front side: a rigid move of the whole map
    is no error, the back side moved alone is, by the planted amount (rotation and translation)."""
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("xyz", [3.0, -5.0, 40.0], degrees=True).as_matrix()
    G[:3, 3] = [0.4, -1.0, 0.2]
    _write_map_trajectories(result_dir, truth, kit, np.eye(4), G)
    m = evaluate_result(truth_path, result_dir).merge_map
    assert m is not None and m.rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    assert m.translation_error_mm == pytest.approx(0.0, abs=1e-6) and m.n_points == 3

    shift = np.eye(4)
    shift[:3, 3] = [0.010, 0.0, 0.0]
    _write_map_trajectories(result_dir, truth, kit, shift, G)
    rep = evaluate_result(truth_path, result_dir)
    m = rep.merge_map
    assert m is not None and m.translation_error_mm == pytest.approx(10.0, abs=1e-6)
    assert m.rotation_error_deg == pytest.approx(0.0, abs=1e-6)
    assert rep.to_dict()["merge"]["map"]["translation_error_mm"] == pytest.approx(10.0, abs=1e-6)

    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(0.5) * np.array([1.0, 0.0, 0.0])).as_matrix()  # about the row
    _write_map_trajectories(result_dir, truth, kit, turn, np.eye(4))
    m = evaluate_result(truth_path, result_dir).merge_map
    assert m is not None and m.rotation_error_deg == pytest.approx(0.5, abs=1e-6) and m.translation_error_mm > 1.0


def test_merged_map_error_needs_both_map_trajectories(truth_path: Path, result_dir: Path) -> None:
    (result_dir / "trajectory_back_map.tum").unlink()
    rep = evaluate_result(truth_path, result_dir)
    assert rep.merge is not None and rep.merge_map is None and "merge.map" in rep.skipped


def _trunks_json(result_dir: Path, stamps: dict[str, list[float]]) -> None:
    """trunks.json with one trunk per side observed at these stamps (s); a side without stamps has none."""
    sides = {}
    for side, st in stamps.items():
        trunks = [] if not st else [{"id": 0, "base": [0.0, 0.0, 1.2], "axis": [0.0, -1.0, 0.0], "length_m": 0.6,
                                     "diameter_m": 0.07, "band": None, "n_points": 100, "n_observations": len(st),
                                     "flags": [], "observations": [{"keyframe": k, "stamp": s}
                                                                   for k, s in enumerate(st)]}]
        sides[side] = {"frame": f"odom_{side}", "trunks": trunks}
    (result_dir / "trunks.json").write_text(json.dumps({"schema": "orchard_mapping.trunks/1", "sides": sides}))


def test_merged_map_error_on_the_trunk_seeing_sweeps(
    truth_path: Path, result_dir: Path, truth: dict[str, Any], kit: types.SimpleNamespace
) -> None:
    """With trunks.json, the merged map's error is also given with each side's keyframes limited to the
    stamps of its trunk observations: over the whole recording it equals the full figure; a side without
    trunks skips it and says why."""
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec(np.radians(0.5) * np.array([1.0, 0.0, 0.0])).as_matrix()
    _write_map_trajectories(result_dir, truth, kit, turn, np.eye(4))
    span = {side: [float(kit.true_trajectory(truth, side, kit.keyframe_step).stamps[i]) for i in (0, -1)]
            for side in ("front", "back")}
    _trunks_json(result_dir, span)
    rep = evaluate_result(truth_path, result_dir)
    assert rep.merge_map is not None and rep.merge_map_trunk_sweep is not None
    assert rep.merge_map_trunk_sweep.rotation_error_deg == pytest.approx(rep.merge_map.rotation_error_deg, abs=1e-9)
    assert rep.to_dict()["merge"]["map_trunk_sweep"]["rotation_error_deg"] == pytest.approx(0.5, abs=1e-6)
    _trunks_json(result_dir, {"front": span["front"], "back": []})
    rep = evaluate_result(truth_path, result_dir)
    assert rep.merge_map is not None and rep.merge_map_trunk_sweep is None
    assert "back side has no trunk observation" in rep.skipped["merge.map_trunk_sweep"]
