"""benchmarks/single_side.py --baseline (run_baseline: the Open3D dense odometry on every frame of each side,
scored at our keyframe stamps) on the tiny fixture row in bags/ (160x120 at 2 Hz), not on a simulated row."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from orchard_mapping.config import load_config
from orchard_mapping.eval.ground_truth import load_ground_truth

_ROOT = Path(__file__).resolve().parents[3]
_PATH = _ROOT / "benchmarks" / "single_side.py"
_ROW = _ROOT / "bags" / "standard_2trees"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("single_side_bench", _PATH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    try:
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.modules.pop(spec.name, None)


def test_run_baseline_scores_each_side_at_our_keyframe_stamps(bench):
    """Every side gets its scores (it used to stop at a NameError: per_side_fe, a name of run_ours)."""
    gt = load_ground_truth(_ROW / "ground_truth.json")
    # "our keyframes": every other true pose of each side (the baseline is scored at these stamps)
    ours = {"sides": {side: {"keyframe_stamps": gt.sides[side].trajectory.stamps[::2].tolist()}
                      for side in bench.SIDES}}
    out = bench.run_baseline(_ROW, load_config(), "point_to_plane", ours)
    assert out["method"] == "point_to_plane" and sorted(out["sides"]) == sorted(bench.SIDES)
    for side, r in out["sides"].items():
        assert r["frames"] >= 3, (side, r)
        assert 2 <= r["scored_poses"] <= len(ours["sides"][side]["keyframe_stamps"]), (side, r)
        assert r["all_frames"]["n_poses"] == r["frames"], (side, r)
        assert np.isfinite(r["ate_mm"]) and r["processing_s"] > 0, (side, r)
