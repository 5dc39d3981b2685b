"""The odometry node's side-finishing thread, driven in this process with the side map's making stubbed out:
with `exit_after_sides` set (every bag replay), the node is marked done once each side expected has its map
or has failed, and the thread goes on (it used to raise a NameError in `_check_wanted` right after marking
the node done, which stopped the thread: a side after that was never finished)."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from rclpy.parameter import Parameter  # noqa: E402

from orchard_mapping.errors import OrchardMappingError  # noqa: E402


@pytest.fixture
def node():
    from orchard_mapping.ros.rgbd_odometry import RGBDOdometryNode

    rclpy.init()
    n = RGBDOdometryNode()
    try:
        yield n
    finally:
        n._finish.put(None)  # ends the finishing thread
        n._work.put(("stop", None))
        n.destroy_node()
        rclpy.try_shutdown()


def _wait(cond, timeout_s: float = 10.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


def test_check_wanted_marks_the_node_done_once_every_side_is_accounted_for(node):
    node.set_parameters([Parameter("exit_after_sides", value=2)])
    node.counts.finished.append("front")
    node._check_wanted()
    assert not node._done.is_set()
    node.counts.failed.append("back")
    node._check_wanted()
    assert node._done.is_set()


def test_check_wanted_without_exit_after_sides_never_marks_done(node):
    node.counts.finished.extend(["front", "back"])
    node._check_wanted()
    assert not node._done.is_set()


def test_the_finishing_thread_goes_on_after_the_node_is_marked_done(node, monkeypatch):
    """exit_after_sides=1: the first side fails (the node is done, exit code 1), and a second side queued after
    it is still finished and published, the finishing thread still running. Each side is finished on a thread of
    its own, so the two outcomes come in either order: the test waits for both."""
    import orchard_mapping.ros.rgbd_odometry as mod

    def fake_finish(session, timings, grounds=None, process=None):
        if session.side == "front":
            raise OrchardMappingError("no keyframes")
        return SimpleNamespace(side=session.side, keyframe_poses=[np.eye(4)], cloud_points=np.zeros((5, 3)),
                               trunks=[])

    published = []
    monkeypatch.setattr(mod, "finish_in_child", fake_finish)
    monkeypatch.setattr(node, "_publish_side_map", published.append)
    node.set_parameters([Parameter("exit_after_sides", value=1)])
    finisher = node._threads[1]
    node._finish.put((SimpleNamespace(side="front", frames=3), time.monotonic()))
    node._finish.put((SimpleNamespace(side="back", frames=3), time.monotonic()))
    assert _wait(lambda: node.counts.finished == ["back"] and node.counts.failed == ["front"]
                 and node._done.is_set()), (node.counts, finisher.is_alive())
    assert node.counts.finished == ["back"] and node.counts.failed == ["front"]
    assert node._done.is_set()
    assert [sm.side for sm in published] == ["back"]
    assert finisher.is_alive()


@pytest.fixture
def ground_node():
    from orchard_mapping.ros.rgbd_odometry import RGBDOdometryNode

    rclpy.init(args=["--ros-args", "-p", "ground_fitter:=node", "-p", "ground_fitter_timeout_s:=0.5"])
    n = RGBDOdometryNode()
    try:
        yield n
    finally:
        n._finish.put(None)
        n._work.put(("stop", None))
        n.destroy_node()
        rclpy.try_shutdown()


def test_a_side_waits_for_the_ground_fitters_answer_to_its_own_geometry(ground_node):
    """With ground_fitter:=node the side's geometry is published and the grounds answered for its stamp come back
    (an answer for another stamp is not it); without an answer the side's finishing fits them (None), and the
    status says so."""
    import threading

    from orchard_mapping.core.cylinder import Cylinder
    from orchard_mapping.core.trunks import TrunkGround
    from orchard_mapping.ros.messages import trunk_grounds_to_msg

    node = ground_node
    assert "geometry" in node._side_pubs("front") and "grounds" not in node._side_pubs("front")
    info = {"side": "front", "frame_id": "odom_front", "stamp": 7.25, "keyframes": 3, "cloud_points": 10}
    ground = TrunkGround(0, ((0, 0), (2, 1)), np.arange(5), Cylinder(np.array([0.0, -1.0, 0.0]),
                                                                     np.array([0.1, 0.3, 1.2]), 0.03),
                         -0.3, 0.4, None, None)

    def answer() -> None:
        time.sleep(0.1)
        node._on_grounds("front", trunk_grounds_to_msg([ground], "front", "odom_front", 3.0))  # another side's end
        node._on_grounds("front", trunk_grounds_to_msg([ground], "front", "odom_front", 7.25))

    threading.Thread(target=answer, daemon=True).start()
    got = node._ask_ground_fitter(info, b"payload")
    assert got is not None and len(got) == 1 and got[0].detections == ((0, 0), (2, 1))
    np.testing.assert_array_equal(got[0].point_indices, np.arange(5))
    assert got[0].ground is None and got[0].wide_ground is None and node.counts.grounds_here == []
    assert node._ask_ground_fitter({**info, "stamp": 9.5}, b"payload") is None  # no answer within 0.5 s
    assert node.counts.grounds_here == ["front"] and not node.errors


def test_a_restarted_node_publishes_again_the_side_maps_its_predecessor_published(tmp_path, monkeypatch):
    """Under `orchard-map launch` each side map published is kept in the graph's scratch folder: a node started
    again after a death publishes them again (a latched message goes with its publisher), without counting them
    as finished (a replay maps them again)."""
    import importlib.util
    from pathlib import Path

    from orchard_mapping_msgs.msg import SideMap as SideMapMsg

    from orchard_mapping.io.sidemap_codec import decode_side_map, encode_side_map
    from orchard_mapping.ros.qos import LATCHED
    from orchard_mapping.ros.rgbd_odometry import RGBDOdometryNode

    spec = importlib.util.spec_from_file_location(
        "sidemap_codec_cases", Path(__file__).parents[1] / "unit" / "io" / "test_sidemap_codec.py")
    cases = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(cases)
    sm = cases._side_map(np.random.default_rng(3))
    monkeypatch.setenv("ORCHARD_GRAPH_SCRATCH", str(tmp_path))
    (tmp_path / "rgbd_odometry").mkdir()
    (tmp_path / "rgbd_odometry" / "side_map_front.bin").write_bytes(encode_side_map(sm))
    rclpy.init()
    got = []
    try:
        listener = rclpy.create_node("side_map_listener")
        listener.create_subscription(SideMapMsg, "/orchard/front/side_map", got.append, LATCHED)
        node = RGBDOdometryNode()
        try:
            deadline = time.monotonic() + 30
            while not got and time.monotonic() < deadline:
                rclpy.spin_once(listener, timeout_sec=0.1)
            assert got and decode_side_map(bytes(got[0].data)).keyframe_stamps.tolist() == sm.keyframe_stamps.tolist()
            assert node.counts.finished == []
            # a side map published is kept for the next start
            (tmp_path / "rgbd_odometry" / "side_map_front.bin").unlink()
            node._publish_side_map(sm)
            assert (tmp_path / "rgbd_odometry" / "side_map_front.bin").read_bytes() == encode_side_map(sm)
        finally:
            node._finish.put(None)
            node._work.put(("stop", None))
            node.destroy_node()
            listener.destroy_node()
    finally:
        rclpy.try_shutdown()
