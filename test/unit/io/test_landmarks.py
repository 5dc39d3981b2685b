"""trunks.json / grounds.json (io.landmarks): written atomically, read back, malformed fields named."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orchard_mapping.core.cylinder import Cylinder, CylinderFit
from orchard_mapping.core.detection import CLASS_TRUNK, Detection
from orchard_mapping.core.ground import LocalGroundFit
from orchard_mapping.core.trunks import TrunkLandmark, TrunkObservation
from orchard_mapping.errors import ResultFormatError
from orchard_mapping.io.landmarks import read_grounds, read_trunks, write_grounds, write_trunks


def _landmark(i: int, hidden: bool = False) -> TrunkLandmark:
    axis = np.array([0.0, -1.0, 0.0])
    cyl = Cylinder(axis, np.array([0.1 * i, 0.3, 1.25]), 0.034)
    band = None if hidden else CylinderFit(cyl, 500, 0.002, 1.1, 3000, True)
    mask = np.zeros((8, 8), bool)
    mask[2:6, 3:5] = True
    obs = [TrunkObservation(k, 100.0 + k, Detection.from_mask(mask, CLASS_TRUNK, 0.9),
                            None if hidden else cyl, 6) for k in range(2)]
    ground = LocalGroundFit(-axis, 0.6, np.array([0.1 * i, 0.6, 1.25]), 900, 0.005, 2000)
    return TrunkLandmark(id=i, axis=axis, base=ground.point, length_m=0.6, ground=ground, band=band,
                         diameter_m=None if hidden else 0.068, baseline_band=band, n_points=1200,
                         observations=obs, flags=["hidden_at_diameter_height"] if hidden else [])


def test_round_trip_keeps_what_the_evaluator_and_the_merge_read(tmp_path):
    sides = {"front": ("odom_front", [_landmark(0), _landmark(1, hidden=True)]), "back": ("odom_back", [])}
    write_trunks(tmp_path / "trunks.json", sides, 0.3)
    write_grounds(tmp_path / "grounds.json", sides)
    trunks = read_trunks(tmp_path / "trunks.json")
    assert [(t.side, t.id) for t in trunks] == [("front", 0), ("front", 1)]
    assert trunks[0].diameter_m == pytest.approx(0.068) and trunks[1].diameter_m is None
    assert trunks[1].flags == ("hidden_at_diameter_height",)
    np.testing.assert_allclose(trunks[0].stamps, [100.0, 101.0])
    doc = json.loads((tmp_path / "trunks.json").read_text())
    assert doc["sides"]["back"]["trunks"] == []  # a side without trunks lists none
    assert doc["sides"]["front"]["trunks"][0]["observations"][0]["box"] == [3.0, 2.0, 5.0, 6.0]
    grounds = read_grounds(tmp_path / "grounds.json")
    assert [(g.side, g.trunk_id) for g in grounds] == [("front", 0), ("front", 1)]
    np.testing.assert_allclose(grounds[0].normal, [0.0, 1.0, 0.0])


def test_a_malformed_field_is_named(tmp_path):
    write_trunks(tmp_path / "trunks.json", {"front": ("odom_front", [_landmark(0)])}, 0.3)
    doc = json.loads((tmp_path / "trunks.json").read_text())
    doc["sides"]["front"]["trunks"][0]["axis"] = [0, 1]
    (tmp_path / "trunks.json").write_text(json.dumps(doc))
    with pytest.raises(ResultFormatError, match=r"trunks\.json: field 'sides\.front\.trunks\[0\]\.axis'"):
        read_trunks(tmp_path / "trunks.json")
    (tmp_path / "grounds.json").write_text(json.dumps({"schema": "other", "sides": {}}))
    with pytest.raises(ResultFormatError, match=r"grounds\.json: field 'schema'"):
        read_grounds(tmp_path / "grounds.json")
