"""The node graph against `orchard-map run`: `orchard-map launch --bag front --bag back --record --out`
replays both sides of the 2-tree standard row at 1x (player, odometry, trunk detector, local ground fitter,
side merger, trait reporter and recorder each in its own process, loopback DDS) with a CPU hog beside it: the
side maps hold the trunks the offline run found, at the same places, no frame is lost on the way, and the
trees published (TreeTraitsArray, decoded from the recording) and written are the offline run's. The result
must not depend on the machine's load: no wall-clock deadline decides it (docs/ros.md). Nodes killed mid-row:
test_graph_faults.py."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

pytest.importorskip("rclpy")

from graph_checks import same_trees  # noqa: E402

from orchard_mapping.cli.main import app  # noqa: E402
from orchard_mapping.io.bags import iter_messages, iter_raw  # noqa: E402
from orchard_mapping.io.landmarks import read_trunks  # noqa: E402
from orchard_mapping.io.results import read_trees, read_tum  # noqa: E402
from orchard_mapping.resources import config_dir  # noqa: E402
from orchard_mapping.ros.tf import transform_of  # noqa: E402


def _cylinders(bag, side: str):
    """(frame id, [(tree id, base (3,), radius)]) of the last TrunkCylinderArray of a side in a recorded bag."""
    msgs = [m for _, m in iter_messages(bag, f"/orchard/{side}/trunk_cylinders")]
    assert len(msgs) == 1, len(msgs)
    m = msgs[-1]
    return m.header.frame_id, [(int(c.tree_id), np.array([c.base.x, c.base.y, c.base.z]), float(c.radius))
                               for c in m.cylinders]


def test_launched_graph_on_bags_gives_the_offline_trunks(standard_row, tmp_path, cpu_hog):
    sim, offline = standard_row
    params = yaml.safe_load((config_dir() / "ros_params.yaml").read_text())
    params["/**"]["ros__parameters"]["trunks"].update(source="masks", masks_dir=str(sim / "masks"))
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    rec, out = tmp_path / "recorded", tmp_path / "out"
    res = CliRunner().invoke(app, ["launch", "--bag", str(sim / "front"), "--bag", str(sim / "back"),
                                   "--record", str(rec), "--params", str(tmp_path / "params.yaml"), "--out", str(out)])
    assert res.exit_code == 0, res.output[-4000:]
    assert "trait_reporter finished: stopping the graph" in res.output, res.output[-4000:]
    assert cpu_hog.cpu_seconds() > 10 or not cpu_hog.procs  # the hog ran beside the graph

    status = [json.loads(m.data) for _, m in iter_messages(rec, "/orchard/odometry/status")][-1]
    sent = sum(1 for bag in ("front", "back") for _ in iter_raw(sim / bag, ["/camera/color/image_raw"]))
    # every colour image the player sent was received, paired and tracked: none lost at 1x
    assert status["colour"] == status["paired"] == sent, status
    assert status["unpaired"] == status["missed"] == status["lost_vs_player"] == 0, status
    assert sum(status["processed"].values()) == sent and not status["errors"], status
    assert status["finished"] == ["front", "back"], status
    # every detection request was answered (a late answer is waited for: nothing flagged for the load)
    assert sum(status["detector_unanswered"].values()) == 0, status
    # the local_ground_fitter node answered both sides (the odometry node fitted no grounds itself)
    assert status["grounds_here"] == [], status
    # (a landmark found to be a trellis post has a ground there too, and is no trunk of trunks.json)
    grounds = [m for _, m in iter_messages(rec, "/orchard/front/local_grounds")]
    assert len(grounds) == 1 and len(grounds[0].grounds) >= sum(t.side == "front" for t in
                                                                read_trunks(offline / "trunks.json")) > 0

    written = read_trunks(offline / "trunks.json")
    for side in ("front", "back"):
        frame, live = _cylinders(rec, side)
        assert frame == f"odom_{side}"
        want = [t for t in written if t.side == side]
        assert [i for i, _, _ in live] == [t.id for t in want] and want, (side, live, want)
        for (_, base, radius), t in zip(live, want, strict=True):
            assert np.abs(base - t.base).max() < 1e-3, (side, base, t.base)  # within 1 mm
            if t.diameter_m is not None:
                assert abs(2 * radius - t.diameter_m) < 1e-3, (side, radius, t.diameter_m)
        path = [m for _, m in iter_messages(rec, f"/orchard/{side}/keyframes")][-1]
        assert len(path.poses) > 20 and path.header.frame_id == f"odom_{side}"

    # the trees: published by the trait reporter, as the offline run wrote them
    same_trees(rec, out, offline)
    merge = json.loads((out / "side_merge.json").read_text())
    offline_merge = json.loads((offline / "side_merge.json").read_text())
    assert merge["method"] == offline_merge["method"] == "semantic_ba"
    _same_tf(rec, np.array(offline_merge["T_front_back"]))
    markers = [m for _, m in iter_messages(rec, "/orchard/tree_markers")][-1]
    trees = read_trees(offline / "trees.json")
    # DELETEALL, then a trunk and a label per tree, and a crown box per tree whose height was measured
    assert len(markers.markers) == 1 + 2 * len(trees) + sum(t.height_m is not None for t in trees)


def _same_tf(rec, T_front_back: np.ndarray) -> None:
    """/tf carries each side's camera in its odom frame, at the pose of the `odometry` message of the same
    stamp; /tf_static puts odom_front at map and odom_back at the offline merge's transform (within 1 mm and
    0.01 deg). (The recorder subscribes to a topic once it sees it: a volatile topic's first message or two
    may come before that.)"""
    def ns(h) -> int:
        return h.stamp.sec * 1_000_000_000 + h.stamp.nanosec

    tf = [t for _, m in iter_messages(rec, "/tf") for t in m.transforms]
    for side in ("front", "back"):
        odom = {ns(m.header): m for _, m in iter_messages(rec, f"/orchard/{side}/odometry")}
        cam = [t for t in tf if t.header.frame_id == f"odom_{side}"]
        assert len(cam) >= len(odom) - 2 and len(odom) > 20, (len(cam), len(odom))
        assert {t.child_frame_id for t in cam} == {m.child_frame_id for m in odom.values()}
        both = [(t, odom[ns(t.header)]) for t in cam if ns(t.header) in odom]
        assert len(both) >= len(odom) - 4, (len(both), len(odom))
        for t, m in both:
            p, q = m.pose.pose.position, m.pose.pose.orientation
            r = t.transform.rotation
            assert np.abs(transform_of(t)[:3, 3] - [p.x, p.y, p.z]).max() < 1e-9
            assert abs(abs(np.dot([r.x, r.y, r.z, r.w], [q.x, q.y, q.z, q.w])) - 1) < 1e-9
    static = [m for _, m in iter_messages(rec, "/tf_static")][-1]
    by_child = {t.child_frame_id: t for t in static.transforms}
    assert set(by_child) == {"odom_front", "odom_back"} and {t.header.frame_id for t in static.transforms} == {"map"}
    assert np.abs(transform_of(by_child["odom_front"]) - np.eye(4)).max() < 1e-12
    D = np.linalg.inv(T_front_back) @ transform_of(by_child["odom_back"])
    assert np.abs(D[:3, 3]).max() < 1e-3 and np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 0.01


def test_one_drive_round_the_row_in_one_bag_gives_the_offline_trees(loop_row, tmp_path):
    """`orchard-map launch --bag loop --drive`: one bag of a continuous drive round the row, its side topic
    ignored (input.side_source=trajectory): the odometry node tells the sides by the camera's U-turn, as
    `run` did on the same bag, and the graph publishes and writes the offline trees."""
    sim, offline = loop_row
    params = yaml.safe_load((config_dir() / "ros_params.yaml").read_text())
    p = params["/**"]["ros__parameters"]
    p["trunks"].update(source="masks", masks_dir=str(sim / "masks" / "loop"))
    p["input"]["side_source"] = "trajectory"
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    rec, out = tmp_path / "recorded", tmp_path / "out"
    res = CliRunner().invoke(app, ["launch", "--bag", str(sim / "loop"), "--drive", "--record", str(rec),
                                   "--params", str(tmp_path / "params.yaml"), "--out", str(out)])
    assert res.exit_code == 0, res.output[-4000:]
    status = [json.loads(m.data) for _, m in iter_messages(rec, "/orchard/odometry/status")][-1]
    sent = sum(1 for _ in iter_raw(sim / "loop", ["/camera/color/image_raw"]))
    assert status["colour"] == status["paired"] == sent and status["lost_vs_player"] == 0, status
    assert status["finished"] == ["front", "back"] and not status["errors"], status
    # the sides split where the offline run split them
    for side in ("front", "back"):
        path = [m for _, m in iter_messages(rec, f"/orchard/{side}/keyframes")][-1]
        stamps = [ps.header.stamp.sec + 1e-9 * ps.header.stamp.nanosec for ps in path.poses]
        assert np.allclose(stamps, read_tum(offline / f"trajectory_{side}.tum").stamps, atol=1e-6), side
    same_trees(rec, out, offline)
