"""Faults in the live graph: nodes killed (SIGKILL) mid-row while `orchard-map launch --bag front --bag back
--record --out` replays the 2-tree standard row, with a CPU hog beside it. The supervisor starts each node again,
nothing recorded is lost, and the run ends with the offline run's trees: what a node had received comes back
to it (latched results, the latched detection request, and for the odometry node the recording again from its
start), and no wall-clock deadline decides a result (docs/ros.md, "When a node dies")."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("rclpy")

from graph_checks import COLOUR, alive, launch_and_kill, mask_params, odometry_status, same_trees  # noqa: E402

from orchard_mapping.io.bags import iter_messages, iter_raw  # noqa: E402

# `make test-slow` (and CI): two replays of the whole graph with a CPU hog beside them, ~4.5 minutes
pytestmark = pytest.mark.slow


def test_detector_ground_fitter_merger_reporter_and_recorder_killed_mid_row(standard_row, tmp_path, cpu_hog):
    """In one replay: the trunk detector and the recorder are killed after the detector answered 10 requests of
    the front side, the ground fitter once it answered the front side's geometry, the side merger and the trait
    reporter once the merger holds the front side map. Each is reported and started again; the run ends with
    the offline trees, none flagged for a gap (the detector's restart cost no keyframe its detections, the
    ground fitter answered both sides); the recorder's bag holds what the killed recorder wrote, each latched
    result once."""
    sim, offline = standard_row
    rec, out = tmp_path / "recorded", tmp_path / "out"
    params = mask_params(sim, tmp_path / "params.yaml")
    kills = [
        (lambda line: "[trunk_detector]" in line and "answered 10 requests" in line, ("trunk_detector", "recorder")),
        (lambda line: "[local_ground_fitter]" in line and "front side:" in line and "trunk landmarks" in line,
         ("local_ground_fitter",)),
        (lambda line: "[side_merger]" in line and "front side map:" in line, ("side_merger", "trait_reporter")),
    ]
    killed_at: dict[str, float] = {}
    rc, text, killed = launch_and_kill(["--bag", str(sim / "front"), "--bag", str(sim / "back"), "--record", str(rec),
                                        "--params", str(params), "--out", str(out)], kills, killed_at=killed_at)
    assert killed == ["trunk_detector", "recorder", "local_ground_fitter", "side_merger", "trait_reporter"], \
        (killed, text[-6000:])
    assert rc == 0, text[-6000:]
    for node in killed:
        assert f"{node} died (exit code -9)" in text and f"{node} restarted (1 of at most 3)" in text, (node, text[-6000:])
    assert "carried on the bag of a recorder that was killed" in text, text[-6000:]
    assert cpu_hog.cpu_seconds() > 10 or not cpu_hog.procs  # the hog ran beside the graph

    status = odometry_status(rec)
    assert status["finished"] == ["front", "back"] and not status["errors"], status
    # every request was answered (the killed detector's by the restarted one), the fitter answered both sides
    assert sum(status["detector_unanswered"].values()) == 0 and status["grounds_here"] == [], status
    same_trees(rec, out, offline)  # ... with the offline flags: none for the faults

    # the bag: what the killed recorder wrote is there (the front side's poses before the kill, its log times the
    # recorders' clock), the poses after the restart too, and the latched results once each
    front, back = (np.array([m.log_time_ns for m in iter_raw(rec, [f"/orchard/{side}/odometry"])]) / 1e9
                   for side in ("front", "back"))
    assert (front < killed_at["recorder"]).sum() > 10 and (back > killed_at["recorder"]).sum() > 100, \
        (len(front), front.min() - killed_at["recorder"], len(back))
    for side in ("front", "back"):
        for topic in ("trunk_cylinders", "side_map", "keyframes", "cloud"):
            assert len(list(iter_messages(rec, f"/orchard/{side}/{topic}"))) == 1, (side, topic)
    assert len(list(iter_messages(rec, "/orchard/side_merge"))) == 1


def test_odometry_killed_mid_row_gets_the_recording_again(standard_row, tmp_path, cpu_hog):
    """The odometry node is killed mid-row, while it tracks the back side and finishes the front side in a child
    process (killed with it). The supervisor starts it again and the bag player with it, from the recording's
    start, so the new node receives every frame and the run ends with the offline trees. The keyframe spool the
    killed node left and the graph's scratch folder are gone at the end."""
    sim, offline = standard_row
    rec, out, tmp = tmp_path / "recorded", tmp_path / "out", tmp_path / "tmp"
    tmp.mkdir()
    params = mask_params(sim, tmp_path / "params.yaml")
    # the back side's first frame: the front side's finishing process has been running since the side ended
    kills = [(lambda line: "[rgbd_odometry]" in line and "back side: tracking" in line, ("rgbd_odometry",))]
    orphans: list[int] = []
    rc, text, killed = launch_and_kill(["--bag", str(sim / "front"), "--bag", str(sim / "back"), "--record", str(rec),
                                        "--params", str(params), "--out", str(out)], kills, env={"TMPDIR": str(tmp)},
                                       orphans=orphans)
    assert killed == ["rgbd_odometry"], text[-6000:]
    assert rc == 0, text[-6000:]
    assert orphans and not any(alive(p) for p in orphans), orphans  # its finishing process went with it
    assert "rgbd_odometry died (exit code -9)" in text and "rgbd_odometry restarted (1 of at most 3)" in text
    assert "player started again from its beginning" in text, text[-6000:]
    assert cpu_hog.cpu_seconds() > 10 or not cpu_hog.procs

    status = odometry_status(rec)  # the new node's: it received the whole recording
    sent = sum(1 for bag in ("front", "back") for _ in iter_raw(sim / bag, [COLOUR]))
    assert status["colour"] == status["paired"] == sent and status["lost_vs_player"] == 0, status
    assert status["finished"] == ["front", "back"] and sum(status["detector_unanswered"].values()) == 0, status
    same_trees(rec, out, offline)
    # the scratch folder (with the killed node's spool in it) was removed: no spool is left in the temp folder
    left = [p.name for p in tmp.iterdir() if p.name.startswith(("orchard-graph-", "orchard-keyframes-"))]
    assert not left, left
    kf = [m for _, m in iter_messages(rec, "/orchard/front/keyframes")][-1]
    assert len(kf.poses) > 20 and np.isfinite(kf.poses[0].pose.position.x)
