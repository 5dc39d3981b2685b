"""The odometry node's client of the trunk detector node (ros/remote_detector.py), in this process: an answer is
waited for however late it comes (no deadline decides a keyframe's detections), an answer to another request is
not this one's, a refusal ends the wait at once, and only a detector gone for good meets the guard, after which
the next keyframes do not wait until a detector answers again."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from orchard_mapping.ros.detections import detections_to_msg, refusal_msg  # noqa: E402
from orchard_mapping.ros.remote_detector import RemoteDetector  # noqa: E402

COLOUR = np.zeros((3, 4, 3), np.uint8)


@pytest.fixture
def node():
    rclpy.init()
    n = rclpy.create_node("remote_detector_test")
    try:
        yield n
    finally:
        n.destroy_node()
        rclpy.try_shutdown()


def _later(seconds: float, fn) -> None:
    t = threading.Timer(seconds, fn)
    t.daemon = True
    t.start()


def _answer(stamp: float):
    return detections_to_msg([], stamp, "camera", 4, 3)


def test_a_late_answer_is_used_and_one_to_another_request_is_not(node):
    det = RemoteDetector(node, "front", "camera", guard_s=60.0)
    _later(0.3, lambda: det._on_answer(_answer(4.0)))  # a restarted detector answering an earlier request
    _later(1.5, lambda: det._on_answer(_answer(5.0)))  # far later than the old 5 s deadline would allow here
    t0 = time.monotonic()
    assert det(COLOUR, 5.0) == []
    assert time.monotonic() - t0 >= 1.4 and det.unanswered == det.refused == det.guard_expired == 0


def test_a_refusal_ends_the_wait_at_once(node):
    det = RemoteDetector(node, "front", "camera", guard_s=60.0)
    _later(0.2, lambda: det._on_answer(refusal_msg(6.0, "camera")))
    t0 = time.monotonic()
    assert det(COLOUR, 6.0) is None
    assert time.monotonic() - t0 < 30 and det.refused == det.unanswered == 1 and det.guard_expired == 0


def test_a_detector_gone_for_good_meets_the_guard_and_costs_the_next_keyframes_nothing(node):
    det = RemoteDetector(node, "front", "camera", guard_s=0.5)
    assert det(COLOUR, 1.0) is None and det.guard_expired == det.unanswered == 1
    t0 = time.monotonic()
    assert det(COLOUR, 2.0) is None  # no wait while the detector is taken to be gone
    assert time.monotonic() - t0 < 0.3 and det.guard_expired == 2
    det._on_answer(_answer(2.0))  # a detector is back (answering the latched request)
    _later(0.2, lambda: det._on_answer(_answer(3.0)))
    assert det(COLOUR, 3.0) == [] and det.unanswered == 2
