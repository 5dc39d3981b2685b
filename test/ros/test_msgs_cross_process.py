"""orchard_mapping_msgs works in rclpy: imports, serialisation, and a real
TrunkCylinderArray crossing from one process to another over DDS (loopback)."""

import importlib
import json
import math
import os
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

rclpy = pytest.importorskip("rclpy")
import orchard_mapping_msgs.msg as oms  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

HERE = Path(__file__).resolve().parent
TIMEOUT_S = 30.0
EXPECTED_TYPES = {
    "TrunkCylinder",
    "TrunkDetection",
    "TrunkDetectionArray",
    "SideMap",
    "TrunkCylinderArray",
    "LocalGround",
    "LocalGroundArray",
    "TreeTraits",
    "TreeTraitsArray",
    "SideMerge",
}


def _message_classes():
    return {
        name: getattr(oms, name)
        for name in dir(oms)
        if not name.startswith("_") and hasattr(getattr(oms, name), "get_fields_and_field_types")
    }


def test_message_package_imports():
    assert set(_message_classes()) == EXPECTED_TYPES
    msg = oms.TrunkCylinderArray()
    assert list(msg.cylinders) == []
    assert type(msg).__module__.startswith("orchard_mapping_msgs.msg")


# --- serialisation round trip of every type -------------------------------------


def _msg_class(type_name: str):
    pkg, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def _value(type_name: str, seed: int):
    """A non-default value of a rosidl field type, different for each seed."""
    if type_name.startswith("sequence<"):
        inner = type_name[len("sequence<") : -1].split(",")[0]
        return [_value(inner, seed + k) for k in range(2)]
    if type_name.endswith("]"):  # a fixed-size array, e.g. float[4]
        inner, n = type_name[:-1].split("[")
        return [_value(inner, seed + k) for k in range(int(n))]
    if type_name in ("double", "float"):
        return 0.25 + 1.5 * seed
    if type_name in ("int8", "int16", "int32", "int64"):
        return -3 - seed
    if type_name in ("uint8", "uint16", "uint32", "uint64", "byte", "octet"):
        return 3 + seed
    if type_name == "boolean":
        return True
    if type_name == "string":
        return f"s{seed}"
    if "/" in type_name:
        return _filled(_msg_class(type_name), seed)
    raise AssertionError(f"no test value for field type {type_name!r}")


def _filled(cls, seed: int = 1):
    msg = cls()
    for k, (field, type_name) in enumerate(cls.get_fields_and_field_types().items()):
        setattr(msg, field, _value(type_name, seed + k))
    return msg


@pytest.mark.parametrize("name", sorted(EXPECTED_TYPES))
def test_serialization_round_trip(name):
    cls = _message_classes()[name]
    msg = _filled(cls)
    assert msg != cls(), "the filled message should differ from the default one"
    data = serialize_message(msg)
    assert isinstance(data, bytes) and len(data) > 0
    back = deserialize_message(data, cls)
    assert back == msg
    # the default message round-trips as well
    assert deserialize_message(serialize_message(cls()), cls) == cls()


# --- one TrunkCylinderArray between two processes --------------------------------


def msg_spec() -> dict:
    """Two real-looking trunk cylinders (the publisher process builds the message from this)."""
    return {
        "frame_id": "odom_front",
        "stamp": [1_700_000_123, 456_789_000],
        "cylinders": [
            {
                "tree_id": 3,
                "side": "front",
                "base": [4.125, -1.375, 0.0625],
                "axis": [0.0348995, 0.0, 0.9993908],
                "radius": 0.0734,
                "length": 0.85,
                "radius_stddev": 0.0021,
                "fit_rmse": 0.0047,
                "inlier_count": 1834,
            },
            {
                "tree_id": -1,
                "side": "front",
                "base": [7.5, -1.41, 0.031],
                "axis": [0.0, -0.0174524, 0.9998477],
                "radius": 0.0612,
                "length": 0.62,
                "radius_stddev": "nan",
                "fit_rmse": 0.0063,
                "inlier_count": 977,
            },
        ],
    }


def _same_float(got: float, want) -> bool:
    if want == "nan":
        return math.isnan(got)
    return got == float(want)  # doubles cross DDS bit-exactly


def _assert_matches_spec(msg, spec):
    assert msg.header.frame_id == spec["frame_id"]
    assert [msg.header.stamp.sec, msg.header.stamp.nanosec] == spec["stamp"]
    assert len(msg.cylinders) == len(spec["cylinders"])
    for cyl, want in zip(msg.cylinders, spec["cylinders"], strict=True):
        assert cyl.header.frame_id == spec["frame_id"]
        assert [cyl.header.stamp.sec, cyl.header.stamp.nanosec] == spec["stamp"]
        assert cyl.tree_id == want["tree_id"]
        assert cyl.side == want["side"]
        assert [cyl.base.x, cyl.base.y, cyl.base.z] == want["base"]
        assert [cyl.axis.x, cyl.axis.y, cyl.axis.z] == want["axis"]
        for field in ("radius", "length", "radius_stddev", "fit_rmse"):
            assert _same_float(getattr(cyl, field), want[field]), (field, getattr(cyl, field), want[field])
        assert cyl.inlier_count == want["inlier_count"]


def test_trunk_cylinder_array_crosses_processes():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert "ROS_DOMAIN_ID" in os.environ  # random per test session (test/conftest.py)
    spec = msg_spec()
    topic = f"orchard_test_{uuid.uuid4().hex[:12]}/trunk_cylinders"
    env = dict(os.environ)  # keeps LD_LIBRARY_PATH, ROS_DOMAIN_ID, discovery range

    received = []
    rclpy.init()
    try:
        node = rclpy.create_node("orchard_test_trunk_subscriber")
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=1,
            reliability=ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL,
        )
        node.create_subscription(oms.TrunkCylinderArray, topic, received.append, qos)

        proc = subprocess.Popen(
            [sys.executable, str(HERE / "trunk_publisher.py"), topic, json.dumps(spec), str(TIMEOUT_S)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
            text=True,
        )
        try:
            deadline = time.monotonic() + TIMEOUT_S
            while not received and time.monotonic() < deadline and proc.poll() is None:
                rclpy.spin_once(node, timeout_sec=0.1)
            # the publisher may have exited right after publishing: drain once more
            end = time.monotonic() + 1.0
            while not received and time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.1)
        finally:
            try:
                out, _ = proc.communicate(input="", timeout=TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                out, _ = proc.communicate()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()

    assert received, f"no message within {TIMEOUT_S} s; publisher rc={proc.returncode}, output:\n{out}"
    assert proc.returncode == 0, out
    assert "PUBLISHED" in out, out
    assert len(received) == 1
    _assert_matches_spec(received[0], spec)
