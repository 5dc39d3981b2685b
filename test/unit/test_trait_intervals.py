"""The 90 % intervals of trees.json: the calibrated half-width, the two sides' disagreement added in quadrature
(diameter and height), widened by the flags."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.pipeline.traits import INTERVAL_HALF, INTERVAL_WIDEN, _intervals


def test_the_sides_disagreement_widens_the_diameter_and_height_intervals():
    values = {"trunk_diameter_m": 0.070, "height_m": 2.30, "canopy_volume_m3": 1.0}
    alone = _intervals(values, [], {})
    assert alone["trunk_diameter_m"] == pytest.approx([0.070 - INTERVAL_HALF["trunk_diameter_m"][1],
                                                       0.070 + INTERVAL_HALF["trunk_diameter_m"][1]], abs=1e-5)
    spread = {"trunk_diameter_m": 0.002, "height_m": 0.06}
    both = _intervals(values, [], spread)
    for trait in spread:
        half = float(np.hypot(INTERVAL_HALF[trait][1], spread[trait]))
        assert both[trait] == pytest.approx([values[trait] - half, values[trait] + half], abs=1e-5), trait
    assert both["canopy_volume_m3"] == alone["canopy_volume_m3"]  # no per-side volume
    wide = _intervals(values, ["seen_from_front_only"], spread)
    k = INTERVAL_WIDEN["seen_from_front_only"]
    assert wide["trunk_diameter_m"][1] - values["trunk_diameter_m"] == pytest.approx(
        k * (both["trunk_diameter_m"][1] - values["trunk_diameter_m"]), abs=2e-5)
