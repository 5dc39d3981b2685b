"""Trunk and ground metrics (eval.landmarks via evaluate_result): planted errors come back."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.eval import evaluate_result
from orchard_mapping.io.results import write_tum

DRIFT = np.array([0.05, -0.02, 0.03])  # m: the estimated odom frame is off here; the metrics must not see it


def _to_odom(truth, side, p_world, vec=False):
    T = np.linalg.inv(np.asarray(truth["sides"][side]["T_world_odom"]))
    p = np.asarray(p_world, float)
    return T[:3, :3] @ p if vec else T[:3, :3] @ p + T[:3, 3] + DRIFT


def _trunk(truth, i, tid, *, diameter_add=0.0, tilt_deg=0.0, shift_world=(0.0, 0.0, 0.0)):
    t = truth["trees"][tid]
    axis_w = Rotation.from_euler("x", tilt_deg, degrees=True).apply([0.0, 0.0, 1.0])
    d = t["trunk"]["diameter_m"] + diameter_add
    return {"id": i, "base": _to_odom(truth, "front", np.add(t["position"], shift_world)).tolist(),
            "axis": _to_odom(truth, "front", axis_w, vec=True).tolist(), "length_m": 0.6, "diameter_m": d,
            "diameter_3d_only_m": d + 0.002, "band": None, "n_points": 100, "n_observations": 2, "flags": [],
            "observations": [{"keyframe": 3, "stamp": 100.6}, {"keyframe": 6, "stamp": 101.0}]}


def _ground(truth, trunk_id, tid, *, tilt_deg=0.0, raise_m=0.0):
    t = truth["trees"][tid]
    n_w = Rotation.from_euler("x", tilt_deg, degrees=True).apply([0.0, 0.0, 1.0])
    p = _to_odom(truth, "front", np.add(t["position"], [0.0, 0.0, raise_m]))
    n = _to_odom(truth, "front", n_w, vec=True)
    return {"trunk_id": trunk_id, "normal": n.tolist(), "offset_m": float(-n @ p), "point": p.tolist(),
            "inliers": 100, "rmse_m": 0.005, "candidates": 300}


def test_planted_trunk_and_ground_errors_come_back(truth, truth_path, result_dir, kit):
    # the estimated front trajectory carries the same offset as the landmarks (a drifted odom frame)
    tr = kit.true_trajectory(truth, "front", kit.keyframe_step)
    write_tum(result_dir / "trajectory_front.tum", StampedTrajectory(tr.stamps, tr.positions + DRIFT,
                                                                     tr.quaternions, "odom_front"))
    trunks = [_trunk(truth, 0, 0), _trunk(truth, 1, 1, diameter_add=0.003, tilt_deg=2.0),
              _trunk(truth, 2, 1, shift_world=(1.2, 0.0, 0.0))]  # a false trunk between trees 1 and 2
    trunks[0]["diameter_m"] = trunks[0]["diameter_3d_only_m"] = None  # tree 0: hidden at the diameter height
    trunks[0]["flags"] = ["hidden_at_diameter_height"]
    (result_dir / "trunks.json").write_text(json.dumps({"schema": "orchard_mapping.trunks/1", "sides": {
        "front": {"frame": "odom_front", "trunks": trunks}, "back": {"frame": "odom_back", "trunks": []}}}))
    grounds = [_ground(truth, 0, 0), _ground(truth, 1, 1, tilt_deg=1.5, raise_m=0.008)]
    (result_dir / "grounds.json").write_text(json.dumps({"schema": "orchard_mapping.grounds/1", "sides": {
        "front": {"frame": "odom_front", "grounds": grounds}}}))

    rep = evaluate_result(truth_path, result_dir).to_dict()
    t = rep["trunks"]["front"]
    assert (t["true_in_view"], t["reported"], t["matched"]) == (3, 3, 2)
    assert t["recall"] == pytest.approx(2 / 3) and t["precision"] == pytest.approx(2 / 3)
    assert t["diameter_n"] == 1 and t["hidden_reported"] == 1
    assert t["diameter_mae_mm"] == pytest.approx(3.0, abs=1e-6)
    assert t["diameter_bias_mm"] == pytest.approx(3.0, abs=1e-6)
    assert t["diameter_3d_only_mae_mm"] == pytest.approx(5.0, abs=1e-6)
    assert t["axis_error_deg"] == pytest.approx(1.0, abs=1e-6)  # median of 0 and 2
    g = rep["grounds"]["front"]
    assert g["n"] == 2 and g["reference"] == "full"
    assert g["normal_error_deg_max"] == pytest.approx(1.5, abs=1e-6)
    assert g["height_error_mm_max"] == pytest.approx(8.0, abs=1e-3)
    assert g["height_error_mm_median"] == pytest.approx(4.0, abs=1e-3)
    assert rep["trunks"]["back"]["reported"] == 0 and rep["trunks"]["back"]["recall"] == 0.0


def test_a_seen_ground_is_the_reference_when_the_truth_has_it(truth, tmp_path, result_dir):
    t0 = truth["trees"][0]
    tilted = Rotation.from_euler("y", 3.0, degrees=True).apply([0.0, 0.0, 1.0])
    t0["observed"]["front"]["local_ground"] = {"point": t0["position"], "normal": tilted.tolist(),
                                               "seen_fraction": 0.3}
    path = tmp_path / "gt.json"
    path.write_text(json.dumps(truth))
    (result_dir / "trunks.json").write_text(json.dumps({"schema": "orchard_mapping.trunks/1", "sides": {
        "front": {"frame": "odom_front", "trunks": [_trunk(truth, 0, 0)]}}}))
    g = _ground(truth, 0, 0)  # the full-disk plane: 3 deg off the plane this side saw
    (result_dir / "grounds.json").write_text(json.dumps({"schema": "orchard_mapping.grounds/1", "sides": {
        "front": {"frame": "odom_front", "grounds": [g]}}}))
    rep = evaluate_result(path, result_dir).to_dict()["grounds"]["front"]
    assert rep["reference"] == "seen"
    assert rep["normal_error_deg_median"] == pytest.approx(3.0, abs=0.05)
    assert rep["normal_error_full_deg_median"] == pytest.approx(0.0, abs=0.05)
