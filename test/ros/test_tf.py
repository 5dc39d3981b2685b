"""TF messages: the venv's vendored tf2_msgs/msg/TFMessage is ROS 2 Jazzy's (same type hash, so RViz, Foxglove
and tf2 on a full install read it), and transforms survive the trip through a TFMessage and rclpy's
serialisation."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from orchard_mapping.ros.tf import transform_msg, transform_of  # noqa: E402

# rosidl's hash of tf2_msgs/msg/TFMessage as ROS 2 Jazzy ships it (`ros2 topic info -v /tf` prints it)
JAZZY_TFMESSAGE_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def test_the_vendored_tfmessage_has_jazzys_type_hash():
    desc = Path(sys.prefix) / "share" / "tf2_msgs" / "msg" / "TFMessage.json"
    if not desc.exists():
        pytest.skip(f"tf2_msgs is not the vendored one here ({desc} missing): a full ROS 2 install")
    hashes = {h["type_name"]: h["hash_string"] for h in json.loads(desc.read_text())["type_hashes"]}
    assert hashes["tf2_msgs/msg/TFMessage"] == JAZZY_TFMESSAGE_HASH


def test_transforms_round_trip_through_a_serialised_tfmessage():
    rng = np.random.default_rng(3)
    Ts = []
    for _ in range(3):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(rng.normal(0, 1.0, 3)).as_matrix()
        T[:3, 3] = rng.normal(0, 5.0, 3)
        Ts.append(T)
    msg = TFMessage(transforms=[transform_msg(T, "odom_front", f"child{i}", 12.5 + i) for i, T in enumerate(Ts)])
    back = deserialize_message(serialize_message(msg), TFMessage)
    for i, (T, t) in enumerate(zip(Ts, back.transforms, strict=True)):
        assert t.header.frame_id == "odom_front" and t.child_frame_id == f"child{i}"
        assert t.header.stamp.sec == 12 + i and t.header.stamp.nanosec == 500_000_000
        assert np.abs(transform_of(t) - T).max() < 1e-9
