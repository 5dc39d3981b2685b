"""The odometry node's pairing of colour and depth images across a side change, driven through its topic
callbacks in this process: the order in which the executor hands over messages of different topics is not
the order they were sent in, so a side message may come before the depth image of the frame sent before it."""

from __future__ import annotations

import queue

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from orchard_mapping.core.sides import SIDE_END  # noqa: E402
from orchard_mapping.ros.messages import stamp_header  # noqa: E402


@pytest.fixture
def node():
    from orchard_mapping.ros.rgbd_odometry import RGBDOdometryNode

    rclpy.init()
    n = RGBDOdometryNode()
    # what the tracking thread would take, read here instead (the thread waits on the queue it was given)
    n._work = queue.Queue()
    info = CameraInfo()
    info.width, info.height = 4, 3
    n._on_info(info)
    try:
        yield n
    finally:
        n.destroy_node()
        rclpy.try_shutdown()


def _image(stamp: float, encoding: str) -> Image:
    img = Image()
    stamp_header(img.header, stamp, "camera")
    img.height, img.width, img.encoding = 3, 4, encoding
    img.step = 4 * (3 if encoding == "rgb8" else 4)
    img.data = np.zeros(img.step * 3, np.uint8).tobytes()
    return img


def _side(name: str) -> String:
    msg = String()
    msg.data = name
    return msg


def _taken(node) -> list[tuple[str, object]]:
    out = []
    while not node._work.empty():
        kind, item = node._work.get_nowait()
        out.append((kind, item if kind == "side" else round(item[0].header.stamp.nanosec / 1e6)))
    return out


def test_a_side_message_before_the_last_frames_depth_waits_for_it(node):
    """Frame 0 (colour, depth), frame 1's colour, then the side change, then frame 1's depth, then frame 2 of
    the new side: frame 1 is paired, and the side change is handed on after it, before frame 2."""
    node._on_colour(_image(0.0, "rgb8"))
    node._on_depth(_image(0.0, "32FC1"))
    node._on_colour(_image(0.1, "rgb8"))
    node._on_side(_side("back"))
    node._on_depth(_image(0.1, "32FC1"))  # overtaken by the side message
    node._on_colour(_image(0.2, "rgb8"))
    node._on_depth(_image(0.2, "32FC1"))
    assert _taken(node) == [("frame", 0), ("frame", 100), ("side", "back"), ("frame", 200)]
    assert node.counts.paired == 3 and node.counts.unpaired == 0


def test_the_end_of_a_recording_flushes_a_colour_image_without_depth(node):
    """No depth follows the end: a colour image still waiting is dropped and counted, the end handed on."""
    node._on_colour(_image(0.0, "rgb8"))
    node._on_depth(_image(0.0, "32FC1"))
    node._on_colour(_image(0.1, "rgb8"))
    node._on_side(_side(SIDE_END))
    assert _taken(node) == [("frame", 0), ("side", SIDE_END)]
    assert node.counts.paired == 1 and node.counts.unpaired == 1


def test_a_side_recorded_again_keeps_one_detector_client(node):
    """A drive that passes a side twice asks the detector node through one client per side, not one more
    publisher and subscription at every start of the side."""
    from rclpy.parameter import Parameter

    from orchard_mapping.ros.trunk_detector import request_topic

    node.set_parameters([Parameter("detector", value="node")])
    info = CameraInfo()
    info.width, info.height = 4, 3
    info.k = [3.0, 0.0, 2.0, 0.0, 3.0, 1.5, 0.0, 0.0, 1.0]
    first = node._new_session("front", _image(0.0, "rgb8"), info)
    again = node._new_session("front", _image(5.0, "rgb8"), info)
    node._new_session("back", _image(2.0, "rgb8"), info)
    assert first.early.detect is again.early.detect
    assert node.count_publishers(request_topic("front")) == 1
    assert node.count_publishers(request_topic("back")) == 1
