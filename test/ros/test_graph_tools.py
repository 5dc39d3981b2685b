"""The node graph's tools, in real processes over loopback DDS: the bag player replays a bag's messages
unchanged and completely, the recorder writes what it hears to a bag, and the supervisor starts, reports,
restarts and stops the nodes (with loopback-only discovery in every node's environment)."""

from __future__ import annotations

import io
import os
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy")

from orchard_mapping.core.types import CameraIntrinsics  # noqa: E402
from orchard_mapping.io.bag_writer import BagWriter
from orchard_mapping.io.bags import iter_messages, iter_raw, read_rgbd  # noqa: E402
from orchard_mapping.ros.supervisor import NodeSpec, Supervisor  # noqa: E402

COLOR = "/camera/color/image_raw"
DEPTH = "/camera/aligned_depth_to_color/image_raw"
INFO = "/camera/color/camera_info"
N_FRAMES = 30
RATE_HZ = 15.0


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    """A 2 s recording at 15 Hz of small random colour and depth images (every frame different)."""
    path = tmp_path_factory.mktemp("bags") / "front"
    intr = CameraIntrinsics(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    rng = np.random.default_rng(7)
    with BagWriter(path) as bag:
        for i in range(N_FRAMES):
            t = 100.0 + i / RATE_HZ
            bag.write_camera_info(INFO, t, intr)
            bag.write_color(COLOR, t, rng.integers(0, 256, (48, 64, 3), dtype=np.uint8))
            bag.write_depth(DEPTH, t, rng.uniform(0.5, 3.0, (48, 64)).astype(np.float32))
    return path


def _run(sup: Supervisor, stop_after_s: float | None = None) -> int:
    if stop_after_s is not None:
        threading.Timer(stop_after_s, sup.stop).start()
    return sup.run()


def test_player_and_recorder_carry_every_message_unchanged(small_bag, tmp_path):
    out = tmp_path / "recorded"
    stats = tmp_path / "player.json"
    log = io.StringIO()
    sup = Supervisor([
        NodeSpec("recorder", "recorder", (str(out), "--prefix", "/camera", "--prefix", "/orchard")),
        NodeSpec("player", "player", (str(small_bag), "--side", "front", "--stats", str(stats)), ends_graph=True),
    ], out=log)
    t0 = time.monotonic()
    assert _run(sup) == 0, log.getvalue()
    wall = time.monotonic() - t0
    assert out.is_dir(), log.getvalue()
    for topic in (COLOR, DEPTH, INFO):
        sent = [m.data for m in iter_raw(small_bag, [topic])]
        got = [m.data for m in iter_raw(out, [topic])]
        assert len(got) == len(sent) == N_FRAMES, (topic, len(got), log.getvalue())
        # the bytes that crossed DDS decode to the same images (rclpy may pad: compare decoded, not raw)
    a, b = list(read_rgbd(small_bag)), list(read_rgbd(out))
    assert len(a) == len(b) == N_FRAMES
    for fa, fb in zip(a, b, strict=True):
        assert fa.stamp == fb.stamp
        assert np.array_equal(fa.color, fb.color) and np.array_equal(fa.depth, fb.depth)
    sides = [m.data for _, m in iter_messages(out, "/orchard/side")]
    assert sides == ["front", "end"], sides
    # original timing: 2 s of recording took about 2 s to replay (not a burst, not a crawl)
    assert wall >= (N_FRAMES - 1) / RATE_HZ, wall


def test_supervisor_gives_every_node_loopback_discovery_and_restarts_a_dead_one(small_bag, tmp_path):
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"  # test/conftest.py
    log = io.StringIO()
    sup = Supervisor([NodeSpec("player", "player", (str(small_bag), "--loop", "--wait", "0"), restart=True)],
                     out=log)
    seen: dict[str, str] = {}

    def kill_then_stop():
        deadline = time.monotonic() + 30
        while "player" not in sup.running and time.monotonic() < deadline:
            time.sleep(0.05)
        pid = sup.running["player"].proc.pid
        environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        seen.update(kv.decode().split("=", 1) for kv in environ if b"=" in kv)
        time.sleep(1.0)
        os.kill(pid, signal.SIGKILL)
        while (sup.running["player"].proc.pid == pid or sup.running["player"].restarts == 0) and \
                time.monotonic() < deadline:
            time.sleep(0.05)
        seen["restarted_pid"] = str(sup.running["player"].proc.pid)
        time.sleep(0.5)
        sup.stop()

    threading.Thread(target=kill_then_stop, daemon=True).start()
    assert sup.run() == 0, log.getvalue()
    assert seen["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert seen["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("fastdds_large_messages.xml")
    # the graph's scratch folder, named to every node, is removed when the graph ends
    assert seen["ORCHARD_GRAPH_SCRATCH"] == str(sup.scratch) and not sup.scratch.exists()
    assert any("player died (exit code -9)" in e for e in sup.events), sup.events
    assert any("player restarted (1 of at most 3)" in e for e in sup.events), sup.events
    assert all(r.proc.poll() is not None for r in sup.running.values())  # nothing left running


def test_supervisor_stops_the_graph_with_exit_1_when_a_node_dies_for_good(tmp_path):
    log = io.StringIO()
    sup = Supervisor([NodeSpec("player", "player", (str(tmp_path / "no_such_bag"),)),
                      NodeSpec("recorder", "recorder", (str(tmp_path / "rec"),))], out=log)
    assert _run(sup) == 1
    text = log.getvalue()
    assert "player died (exit code 2)" in text and "no such file or folder" in text, text
    assert not list(tmp_path.glob(".rec.*"))  # the stopped recorder left no half-written bag behind


def test_a_node_that_fails_for_good_is_not_started_again(tmp_path):
    """An exit code its spec names final (a refused merge, a side that cannot be mapped) stops the graph with 1 at
    once: another start would fail the same way."""
    log = io.StringIO()
    sup = Supervisor([NodeSpec("player", "player", (str(tmp_path / "no_such_bag"),), restart=True,
                               final_codes=(2,))], out=log)
    assert _run(sup) == 1
    assert "player failed (exit code 2): stopping the graph" in log.getvalue() and "restarted" not in log.getvalue()


@pytest.mark.parametrize("bags, drive", [(["front", "back"], False), (["front"], False), (["drive"], True)])
def test_a_replay_waits_for_every_node_asked_during_the_first_frames_and_for_the_detector(bags, drive):
    """The first frame is sent only once the odometry node reads the camera and the nodes it asks (the trunk
    detector, the ground fitter) or feeds at once are up: a node still importing the core when the frames begin would leave the
    first keyframes without detections, and their trunks flagged, on a loaded machine."""
    from orchard_mapping.ros.graph import graph_specs

    specs = {s.name: s for s in graph_specs([Path(b) for b in bags], drive=drive)}
    args = specs["player"].args
    waited = {args[i + 1] for i, a in enumerate(args) if a == "--wait-node"}
    readers = {args[i + 1] for i, a in enumerate(args) if a == "--wait-reader"}
    assert readers == {"rgbd_odometry"}
    assert "trunk_detector" in specs and "trunk_detector" in waited
    # the ground fitter answers each side's geometry: there and waited for on every replay
    assert "local_ground_fitter" in specs and "local_ground_fitter" in waited
    assert "ground_fitter:=node" in specs["rgbd_odometry"].args and specs["local_ground_fitter"].restart
    # the merge's nodes exist only where two sides are merged, and are then waited for too
    assert waited - {"trunk_detector", "local_ground_fitter"} == ({"side_merger", "trait_reporter"} & set(specs))
    # no wall-clock deadline decides a replay's result: the detector's answers are waited for (latched requests,
    # ros/remote_detector.py), side changes are acknowledged by the odometry node, and the player's wait for the
    # nodes is a guard it fails on rather than play to a graph that is not up
    assert not any("timeout" in a for a in specs["rgbd_odometry"].args)
    assert "--side-acks" in args and args[args.index("--wait") + 1] == "600"
    # every node is started again when it dies; the player with the odometry node (the recording again from its
    # start); the recorder, if any, is stopped last
    assert all(s.restart for s in specs.values() if s.name != "player")
    assert specs["rgbd_odometry"].restart_with == ("player",)
    # every node waited for starts before the player
    names = list(specs)
    assert all(names.index(n) < names.index("player") for n in waited | readers)


def test_a_killed_recorder_is_restarted_and_carries_on_its_bag(small_bag, tmp_path):
    """The recorder is killed (SIGKILL) while the player loops over a bag: started again, the new recorder copies
    what the killed one wrote (every message was on disk once written) into its bag and records on; the bag
    closed at the stop holds messages from before the kill and after, and the latched side topic's last
    message, received again, once."""
    out = tmp_path / "recorded"
    log = io.StringIO()
    sup = Supervisor([
        NodeSpec("recorder", "recorder", (str(out), "--prefix", "/camera", "--prefix", "/orchard"), restart=True,
                 stop_last=True),
        NodeSpec("player", "player", (str(small_bag), "--side", "front", "--loop", "--wait", "60"), restart=True),
    ], out=log)
    killed: dict[str, float] = {}

    def kill_then_stop():
        deadline = time.monotonic() + 120
        while "recorder" not in sup.running and time.monotonic() < deadline:
            time.sleep(0.05)
        pid = sup.running["recorder"].proc.pid

        def written() -> int:  # bytes the recorder put on disk so far
            return sum(f.stat().st_size for f in tmp_path.glob(".recorded.*/**/*.mcap"))

        while written() < 600_000 and time.monotonic() < deadline:  # a loop of the bag or so
            time.sleep(0.1)
        os.kill(pid, signal.SIGKILL)
        killed["at"] = time.time()  # the recorder's log times are the system clock's
        while "carried on the bag" not in log.getvalue() and time.monotonic() < deadline:
            time.sleep(0.1)
        # the new recorder records on: until it has put half a loop of the bag more on disk (not a fixed wait,
        # which a loaded machine outlasted: nothing recorded after the kill)
        carried, deadline = written(), time.monotonic() + 120
        while written() < carried + 300_000 and time.monotonic() < deadline:
            time.sleep(0.1)
        sup.stop()

    threading.Thread(target=kill_then_stop, daemon=True).start()
    assert sup.run() == 0, log.getvalue()
    text = log.getvalue()
    assert "recorder died (exit code -9)" in text and "carried on the bag of a recorder that was killed" in text, text
    assert out.is_dir() and not list(tmp_path.glob(".recorded.*")), text  # one bag, closed; no partial left
    colour = np.array([m.log_time_ns for m in iter_raw(out, [COLOR])]) / 1e9
    # what the killed recorder wrote (a loop of the bag or so) and what the new one recorded
    assert (colour < killed["at"]).sum() >= N_FRAMES // 2 and (colour > killed["at"]).sum() > 0, \
        (len(colour), colour.min() - killed["at"], colour.max() - killed["at"])
    # the side topic is latched: its last message, received again by the new recorder, is written once (the loops
    # alternate "front" and "end"; a message written twice would repeat one)
    sides = [m.data for _, m in iter_messages(out, "/orchard/side")]
    assert sides[0] == "front" and all(a != b for a, b in zip(sides, sides[1:], strict=False)), sides
