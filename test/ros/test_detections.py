"""Trunk detections cross the trunk detector's topic unchanged: box, score, class and the full mask."""

import numpy as np
import pytest

pytest.importorskip("rclpy")

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK, Detection  # noqa: E402
from orchard_mapping.ros.detections import detections_from_msg, detections_to_msg  # noqa: E402


def test_detections_round_trip_through_the_message():
    from orchard_mapping_msgs.msg import TrunkDetectionArray

    rng = np.random.default_rng(3)
    trunk = np.zeros((48, 64), bool)
    trunk[5:40, 20:31] = rng.random((35, 11)) > 0.2  # ragged edges: the crop must keep every pixel
    post = np.zeros((48, 64), bool)
    post[0:48, 60:64] = True  # touches the image border
    dets = [Detection.from_mask(trunk, CLASS_TRUNK, 0.93), Detection.from_mask(post, CLASS_POST, 0.51),
            Detection(CLASS_TRUNK, 0.2, np.array([1.5, 2.0, 3.5, 4.0]), np.zeros((48, 64), bool))]  # empty mask
    msg = detections_to_msg(dets, 12.345678901, "camera_color_optical_frame", 64, 48)
    back = detections_from_msg(deserialize_message(serialize_message(msg), TrunkDetectionArray))
    assert msg.header.stamp.sec == 12 and msg.header.stamp.nanosec == 345678901
    assert len(back) == 3
    for a, b in zip(dets, back, strict=True):
        assert a.class_id == b.class_id and abs(a.score - b.score) < 1e-6
        assert np.allclose(a.box, b.box) and np.array_equal(a.mask, b.mask)
    assert len(msg.detections[0].mask) < trunk.size / 4  # cropped, not the whole image
