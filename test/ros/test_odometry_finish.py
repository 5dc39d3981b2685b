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
    it is still finished and published by the same thread."""
    import orchard_mapping.ros.rgbd_odometry as mod

    def fake_finish(session, timings):
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
    assert _wait(lambda: node.counts.finished == ["back"]), (node.counts, finisher.is_alive())
    assert node.counts.failed == ["front"]
    assert node._done.is_set()
    assert [sm.side for sm in published] == ["back"]
    assert finisher.is_alive()
