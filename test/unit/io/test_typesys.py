"""Our message types registered with rosbags' typesys from the shipped .msg files."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.io.typesys import orchard_msgtypes, typestore
from orchard_mapping.resources import msg_dir

OURS = [
    "LocalGround",
    "LocalGroundArray",
    "SideMerge",
    "TreeTraits",
    "TreeTraitsArray",
    "TrunkCylinder",
    "TrunkCylinderArray",
    "TrunkDetection",
    "TrunkDetectionArray",
    "SideMap",
]


def test_every_msg_file_is_registered() -> None:
    names = {p.stem for p in msg_dir().glob("*.msg")}
    assert names == set(OURS)
    assert orchard_msgtypes() == tuple(f"orchard_mapping_msgs/msg/{n}" for n in sorted(OURS))
    for name in orchard_msgtypes():
        assert name in typestore().types


def test_standard_jazzy_types_are_there_and_store_is_cached() -> None:
    store = typestore()
    assert store is typestore()
    for name in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "std_msgs/msg/String"):
        assert name in store.types


@pytest.mark.parametrize(
    ("array", "field", "element"),
    [
        ("TrunkCylinderArray", "cylinders", "TrunkCylinder"),
        ("LocalGroundArray", "grounds", "LocalGround"),
        ("TreeTraitsArray", "trees", "TreeTraits"),
    ],
)
def test_nested_references_resolve_inside_our_package(array: str, field: str, element: str) -> None:
    _, fields = typestore().fielddefs[f"orchard_mapping_msgs/msg/{array}"]
    kinds = dict(fields)
    # (SEQUENCE, ((NAME, 'orchard_mapping_msgs/msg/Element'), 0))
    assert kinds[field][1][0][1] == f"orchard_mapping_msgs/msg/{element}"


def test_cdr_round_trip_of_a_nested_message() -> None:
    store = typestore()
    t = store.types
    header = t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=3, nanosec=7), frame_id="map")
    tree = t["orchard_mapping_msgs/msg/TreeTraits"](
        header=header,
        tree_id=4,
        position=t["geometry_msgs/msg/Point"](x=1.0, y=2.0, z=0.0),
        trunk_diameter=0.12,
        height=2.5,
        canopy_volume=1.75,
        fruit_count=30,
        fruit_count_front=20,
        fruit_count_back=15,
        flags=["trunk_occluded"],
        trunk_id_front=2,
        trunk_id_back=-1,
        trunk_diameter_front=0.118,
        trunk_diameter_back=0.121,
    )
    msg = t["orchard_mapping_msgs/msg/TreeTraitsArray"](header=header, trees=[tree, tree])
    raw = store.serialize_cdr(msg, "orchard_mapping_msgs/msg/TreeTraitsArray")
    back = store.deserialize_cdr(raw, "orchard_mapping_msgs/msg/TreeTraitsArray")
    assert back == msg
    assert isinstance(raw, np.ndarray | bytes | memoryview)
