"""eval.ground_truth: schema and field validation with the file and field named."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from orchard_mapping.errors import GroundTruthError
from orchard_mapping.eval import load_ground_truth


def test_loads_the_documented_schema(truth_path: Path, truth: dict[str, Any]) -> None:
    gt = load_ground_truth(truth_path)
    assert [t.id for t in gt.trees] == [0, 1, 2]
    assert gt.trees[1].diameter_m == pytest.approx(0.065)
    assert gt.trees[2].fruit_positions.shape == (5, 3) and gt.trees[2].fruit_visible["either"] == 4
    assert set(gt.sides) == {"front", "back"}
    assert gt.sides["back"].trajectory.positions.shape == (31, 3)
    np.testing.assert_allclose(gt.T_front_back, truth["T_front_back"])
    assert gt.diameter_height_m == 0.30


def _write(tmp_path: Path, doc: dict[str, Any]) -> Path:
    path = tmp_path / "gt_bad.json"
    path.write_text(json.dumps(doc))
    return path


def test_wrong_schema(tmp_path: Path, truth: dict[str, Any]) -> None:
    truth["schema"] = "orchard_mapping.ground_truth/0"
    with pytest.raises(
        GroundTruthError, match=r"gt_bad\.json: field 'schema': expected 'orchard_mapping.ground_truth/1'"
    ):
        load_ground_truth(_write(tmp_path, truth))


@pytest.mark.parametrize(
    ("drop", "field"),
    [
        (("trees", 1, "trunk", "diameter_m"), "trees[1].trunk.diameter_m"),
        (("trees", 2, "fruit", 0, "radius_m"), "trees[2].fruit[0].radius_m"),
        (("trees", 0, "fruit_visible", "either"), "trees[0].fruit_visible.either"),
        (("sides", "back", "trajectory"), "sides.back.trajectory"),
        (("T_front_back",), "T_front_back"),
    ],
)
def test_missing_field_is_named(tmp_path: Path, truth: dict[str, Any], drop: tuple[Any, ...], field: str) -> None:
    node: Any = truth
    for key in drop[:-1]:
        node = node[key]
    del node[drop[-1]]
    with pytest.raises(GroundTruthError, match=rf"gt_bad\.json: field '{re.escape(field)}': missing"):
        load_ground_truth(_write(tmp_path, truth))


def test_bad_values(tmp_path: Path, truth: dict[str, Any]) -> None:
    truth["trees"][0]["height_m"] = "tall"
    with pytest.raises(GroundTruthError, match=r"field 'trees\[0\]\.height_m': expected a finite number"):
        load_ground_truth(_write(tmp_path, truth))
    truth["trees"][0]["height_m"] = 2.0
    truth["sides"]["front"]["T_world_odom"][0][0] = 2.0
    with pytest.raises(GroundTruthError, match=r"'sides\.front\.T_world_odom': 3x3 block is not a rotation"):
        load_ground_truth(_write(tmp_path, truth))


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(GroundTruthError, match="not found"):
        load_ground_truth(tmp_path / "nope.json")
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(GroundTruthError, match=r"broken\.json: not valid JSON"):
        load_ground_truth(tmp_path / "broken.json")
