"""Trunk landmarks and local grounds <-> TrunkCylinderArray / LocalGroundArray: round trips, also through
rclpy's serialisation (what crosses a topic)."""

from __future__ import annotations

import math
from dataclasses import astuple

import numpy as np
import pytest

pytest.importorskip("rclpy")
from orchard_mapping_msgs.msg import LocalGroundArray, TrunkCylinderArray  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from orchard_mapping.core.cylinder import Cylinder, CylinderFit  # noqa: E402
from orchard_mapping.core.ground import LocalGroundFit  # noqa: E402
from orchard_mapping.core.trunks import TrunkLandmark  # noqa: E402
from orchard_mapping.ros.messages import (  # noqa: E402
    TrunkRecord,
    ground_records,
    grounds_from_msg,
    grounds_to_msg,
    trunks_from_msg,
    trunks_to_msg,
)


def _landmarks() -> list[TrunkLandmark]:
    up = np.array([0.02, -0.999, 0.01]) / np.linalg.norm([0.02, -0.999, 0.01])
    out = []
    for i, hidden in enumerate((False, True)):
        g = LocalGroundFit(-up, 0.61 + i, np.array([0.9 * i, 0.6, 1.3]), 800 + i, 0.004, 1500)
        band = None if hidden else CylinderFit(Cylinder(up, np.array([0.9 * i, 0.3, 1.3]), 0.0342), 640, 0.0021,
                                               1.2, 4000, True)
        out.append(TrunkLandmark(id=i, axis=up, base=g.point, length_m=0.58, ground=g if i == 0 else None,
                                 band=band, diameter_m=None if hidden else 0.0684, baseline_band=band,
                                 n_points=900 + i, observations=[], flags=[]))
    return out


def test_trunks_round_trip_through_a_serialised_message():
    records = [TrunkRecord.from_landmark(lm, "front") for lm in _landmarks()]
    msg = trunks_to_msg(records, "odom_front", 1700000012.25)
    back = deserialize_message(serialize_message(msg), TrunkCylinderArray)
    frame, stamp, got = trunks_from_msg(back)
    assert frame == "odom_front" and stamp == pytest.approx(1700000012.25, abs=1e-6)
    np.testing.assert_equal([astuple(r) for r in got], [astuple(r) for r in records])  # NaN == NaN here
    assert got[0].radius == pytest.approx(0.0342) and got[0].inlier_count == 640
    assert math.isnan(got[1].radius) and got[1].inlier_count == 901  # hidden: no radius, not a made-up one
    assert got[1].base == records[1].base and got[1].tree_id == 1


def test_grounds_round_trip_and_pair_with_their_trunk():
    records = ground_records(_landmarks(), "back")
    assert [r.tree_id for r in records] == [0]  # the trunk without a ground sends none
    msg = deserialize_message(serialize_message(grounds_to_msg(records, "odom_back", 5.5)), LocalGroundArray)
    frame, stamp, got = grounds_from_msg(msg)
    assert (frame, stamp) == ("odom_back", 5.5)
    assert got == records


def test_trees_round_trip_through_tree_traits_array():
    """Result trees -> TreeTraitsArray -> bytes -> trees: every value trees.json keeps (None as NaN / -1)."""
    from orchard_mapping_msgs.msg import TreeTraitsArray

    from orchard_mapping.io.results import ResultTree
    from orchard_mapping.ros.messages import trees_from_msg, trees_to_msg
    from orchard_mapping.ros.trait_reporter import tree_markers

    trees = [
        ResultTree(0, (1.0, -0.5, 2.25), 0.081, per_side={"front": {"trunk_id": 3, "diameter_m": 0.082},
                                                          "back": {"trunk_id": 7, "diameter_m": None}}),
        ResultTree(1, (3.5, -0.4, 2.3), None, flags=("seen_from_back_only", "trunk_hidden_at_diameter_height"),
                   per_side={"back": {"trunk_id": 8, "diameter_m": None}}),
        ResultTree(2, (5.0, -0.45, 2.2), 0.07, height_m=2.4, canopy_volume_m3=1.5, fruit_count=12,
                   extra={"fruit_count_front": 8, "fruit_count_back": 7}),
    ]
    msg = deserialize_message(serialize_message(trees_to_msg(trees, "map", 12.5)), TreeTraitsArray)
    frame, stamp, back = trees_from_msg(msg)
    assert frame == "map" and stamp == pytest.approx(12.5)
    assert [t.to_json() for t in back] == [t.to_json() for t in trees]
    assert msg.trees[1].trunk_id_front == -1 and math.isnan(msg.trees[1].trunk_diameter)
    assert msg.trees[0].fruit_count == -1 and msg.trees[2].fruit_count == 12
    assert msg.trees[0].fruit_count_front == -1 and (msg.trees[2].fruit_count_front, msg.trees[2].fruit_count_back) == (
        8, 7)
    markers = tree_markers(trees, "map", 12.5).markers
    assert len(markers) == 1 + 2 * len(trees) + 1 and markers[2].text == "tree 0: 81 mm"
    crown = markers[-1]  # tree 2: height 2.4 m, 1.5 m3 (no clear trunk given: from its foot)
    assert crown.ns == "crowns" and crown.scale.y == pytest.approx(2.4)
    assert crown.scale.x * crown.scale.y * crown.scale.z == pytest.approx(1.5)
    assert markers[-2].text == "tree 2: 70 mm, 2.40 m, 1.50 m3, 12 fruit"
    assert markers[3].color.g < markers[1].color.g  # seen from one side: orange, from both: green


def test_a_ground_fitters_answer_round_trips_exactly():
    """TrunkGround per landmark -> LocalGroundArray -> bytes -> TrunkGround: the same values to the bit, for a local
    ground, a wide one (no local ground) and none; the plane's fields are the ground's."""
    from orchard_mapping.core.cylinder import Cylinder
    from orchard_mapping.core.trunks import TrunkGround
    from orchard_mapping.ros.messages import trunk_grounds_from_msg, trunk_grounds_to_msg

    rng = np.random.default_rng(3)
    up = np.array([0.02, -0.999, 0.01]) / np.linalg.norm([0.02, -0.999, 0.01])

    def plane(i: int) -> LocalGroundFit:
        return LocalGroundFit(-up, 0.61 + i / 3, rng.normal(size=3), 800 + i, 0.004 / 3, 1500 + i, 0.3 / 7,
                              float("nan") if i else 0.123456789, rng.normal(size=(9 + i, 3)))

    grounds = [TrunkGround(i, ((0, 0), (4, 1), (7, 0))[: i + 1], rng.integers(0, 10**6, 50 + i),
                           Cylinder(up + 1e-9 * i, rng.normal(size=3), 0.0342 + 1e-12), -0.1 / 3, 0.6 + i / 7,
                           plane(i) if i == 0 else None, plane(i) if i == 1 else None) for i in range(3)]
    msg = deserialize_message(serialize_message(trunk_grounds_to_msg(grounds, "back", "odom_back", 5.5)),
                              LocalGroundArray)
    assert [m.kind for m in msg.grounds] == ["local", "wide", "none"]
    frame, stamp, got = trunk_grounds_from_msg(msg)
    assert (frame, stamp) == ("odom_back", 5.5) and len(got) == 3
    for g, w in zip(got, grounds, strict=True):
        assert (g.id, g.detections, g.bottom_m, g.top_m, g.coarse.radius) == (w.id, w.detections, w.bottom_m, w.top_m,
                                                                            w.coarse.radius)
        for a, b in ((g.point_indices, w.point_indices), (g.coarse.axis, w.coarse.axis),
                     (g.coarse.origin, w.coarse.origin)):
            np.testing.assert_array_equal(a, b)
        for a, b in ((g.ground, w.ground), (g.wide_ground, w.wide_ground)):
            assert (a is None) == (b is None)
            if a is not None:
                np.testing.assert_equal(
                    (a.offset, a.inliers, a.rmse_m, a.candidates, a.support_m2, a.support_offset_m),
                    (b.offset, b.inliers, b.rmse_m, b.candidates, b.support_m2, b.support_offset_m))  # NaN == NaN
                for x, y in ((a.normal, b.normal), (a.point, b.point), (a.ground_cells, b.ground_cells)):
                    np.testing.assert_array_equal(x, y)
