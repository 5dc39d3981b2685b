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


def test_a_side_recorded_again_keeps_one_detector_client(node, tmp_path):
    """A drive that passes a side twice asks the detector node through one client per side, not one more
    publisher and subscription at every start of the side."""
    from rclpy.parameter import Parameter

    from orchard_mapping.ros.trunk_detector import request_topic

    # the sessions' keyframe spools in the test's folder (left unclosed here, they piled up in /tmp)
    node.set_parameters([Parameter("detector", value="node"), Parameter("spool_dir", value=str(tmp_path))])
    info = CameraInfo()
    info.width, info.height = 4, 3
    info.k = [3.0, 0.0, 2.0, 0.0, 3.0, 1.5, 0.0, 0.0, 1.0]
    first = node._new_session("front", _image(0.0, "rgb8"), info)
    again = node._new_session("front", _image(5.0, "rgb8"), info)
    node._new_session("back", _image(2.0, "rgb8"), info)
    assert first.early.detect is again.early.detect
    assert node.count_publishers(request_topic("front")) == 1
    assert node.count_publishers(request_topic("back")) == 1


def test_a_players_statement_is_acknowledged_once_the_images_it_names_are_here(node, monkeypatch):
    """Before a side change the player names the stamp of the last colour and depth image it sent: the node
    acknowledges (publishes its status with the stamps received) only once both are here, however late they
    come, counts the colour images lost only then, and acknowledges the side message as it takes it."""
    import json

    statuses = []
    monkeypatch.setattr(node, "_publish_status", lambda: statuses.append(
        {"received_ns": dict(node._received_ns), "last_side": node._last_side}))
    colour, depth = "/camera/color/image_raw", "/camera/aligned_depth_to_color/image_raw"
    node._on_colour(_image(0.0, "rgb8"))
    node._on_depth(_image(0.0, "32FC1"))
    node._on_player(_side(json.dumps({"published": {colour: 3, depth: 3},
                                      "last_ns": {colour: 200_000_000, depth: 200_000_000}})))
    node._on_colour(_image(0.1, "rgb8"))
    node._on_colour(_image(0.2, "rgb8"))
    node._on_depth(_image(0.1, "32FC1"))
    assert statuses == [] and node._statement is not None  # depth 0.2 is not here yet
    node._on_depth(_image(0.2, "32FC1"))
    assert statuses == [{"received_ns": {colour: 200_000_000, depth: 200_000_000}, "last_side": None}]
    assert node._statement is None and node.counts.lost_vs_player == 0
    node._on_side(_side("back"))
    assert statuses[-1]["last_side"] == "back"


def test_the_player_reads_the_stamps_it_names_from_the_stored_bytes():
    """The player names each camera topic's last stamp from the stored message's bytes (no decoding), and reads
    a stored side message's text likewise; a restarted odometry node (an incarnation not known when the images
    were sent) acknowledges them at once."""
    from types import SimpleNamespace

    from rclpy.serialization import serialize_message

    from orchard_mapping.ros.player import BagPlayer, _side_text, header_stamp_ns

    assert header_stamp_ns(serialize_message(_image(1234.5678, "rgb8"))) == 1_234_567_800_000
    assert _side_text(serialize_message(_side("back"))) == "back"
    player = SimpleNamespace(last_ns={"/c": 5, "/d": 7})
    ok = {"incarnation": "a", "received_ns": {"/c": 5, "/d": 7}}
    assert BagPlayer._images_acked(player, ok, {"a"})
    assert not BagPlayer._images_acked(player, {**ok, "received_ns": {"/c": 5, "/d": 6}}, {"a"})
    assert not BagPlayer._images_acked(player, {**ok, "received_ns": {"/c": 5, "/d": None}}, {"a"})
    assert BagPlayer._images_acked(player, {**ok, "incarnation": "b", "received_ns": {"/c": None, "/d": None}}, {"a"})
