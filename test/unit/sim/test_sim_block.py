"""A block of rows and the drive along both sides of each (path mode `block`, sim.block)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orchard_mapping.config import TopicsConfig
from orchard_mapping.core.sides import UTurnSides
from orchard_mapping.errors import ScenarioError
from orchard_mapping.io.bags import describe_bag, read_rgbd
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.scene import Cls, build_scene
from orchard_mapping.sim.trajectory import block_path

SEED = 4


@pytest.fixture(scope="module")
def block():
    """The `block` scenario's scene (3 rows of 2 trees) and its drive at 5 Hz; nothing rendered."""
    sc = load_scenario("block", {"row.n_trees": 2, "camera.rate_hz": 5.0})
    scene = build_scene(sc, SEED)
    return sc, scene, block_path(sc, scene.rows, scene.terrain, np.random.default_rng(0), 0.0)


def test_a_block_is_rows_of_their_own_trees_the_first_as_a_row_alone(block):
    sc, scene, _ = block
    assert [r.number for r in scene.rows] == [1, 2, 3]
    assert [r.y for r in scene.rows] == pytest.approx([0.0, 3.4, 6.8])
    assert [r.tree_ids for r in scene.rows] == [(0, 1), (2, 3), (4, 5)]
    for r in scene.rows:
        for tid in r.tree_ids:
            assert abs(scene.trees[tid].base[1] - r.y) < 0.05  # offset_jitter_m 3 cm
    # each row has its own trellis: two end posts
    assert sorted(round(p["position"][1], 2) for p in scene.posts) == [0.0, 0.0, 3.4, 3.4, 6.8, 6.8]
    # the first row is the row the same scenario and seed give alone: same trees, same terrain
    alone = build_scene(load_scenario("block", {"row.n_trees": 2, "block.rows": 1}), SEED)
    for a, b in zip(alone.trees, scene.trees[:2], strict=True):
        np.testing.assert_array_equal(a.axis_points, b.axis_points)
    np.testing.assert_array_equal(alone.terrain.wave_k, scene.terrain.wave_k)
    # hedges across both ends of the block (headland_m beyond the turns), from one outer hedge to the other
    hedge = scene.vertices[np.unique(scene.triangles[scene.tri_cls == Cls.HEDGE])]
    x_lo = min(r.x[0] for r in scene.rows) - sc.row.margin_m
    across = hedge[np.abs(hedge[:, 0] - (x_lo - sc.block.headland_m)) < 0.2]
    assert across[:, 1].min() < -3.0 and across[:, 1].max() > 6.8 + 3.0


def test_the_drive_goes_along_both_sides_of_every_row_looking_at_it(block):
    sc, scene, drive = block
    d = sc.path.distance_m
    labels = list(zip(drive.rows.tolist(), drive.sides.tolist(), strict=True))
    order = [labels[0]] + [labels[i] for i in range(1, len(labels)) if labels[i] != labels[i - 1]]
    assert order == [(1, "front"), (1, "back"), (2, "front"), (2, "back"), (3, "front"), (3, "back")]
    pos, look = drive.poses[:, :3, 3], drive.poses[:, :3, 2]
    for r in scene.rows:
        for side, sgn in (("front", -1.0), ("back", 1.0)):
            m = (drive.rows == r.number) & (drive.sides == side)
            # the pass itself, not its turns: on its line, away from the block's ends
            along = m & (np.abs(pos[:, 1] - (r.y + sgn * d)) < 0.05) & (np.abs(pos[:, 0] - sum(r.x) / 2) < 1.2)
            assert along.sum() > 0.3 * m.sum()
            # looking across at the row (+y from the front, -y from the back), level (jitter 0.8 deg)
            assert np.all(-sgn * look[along, 1] > 0.99)
            # and along its whole length, trunks included
            assert pos[along, 0].min() < r.x[0] - 0.5 and pos[along, 0].max() > r.x[1] + 0.5


def test_the_product_cuts_the_true_drive_where_the_simulator_labels_it(block):
    """core.sides on the drive's true poses (each side in its own odom frame) gives the simulator's rows and
    sides, each cut within 2 frames (9 deg of a turn at 5 Hz) of the simulator's, half way round each turn: a
    side's reference heading is the last one turned by half a turn about the turn's axis, which the hand-held
    jitter (0.8 deg) tilts a little at each turn."""
    _, _, drive = block
    det, origin, got = UTurnSides(), None, []
    for T in drive.poses:
        origin = T if origin is None else origin
        got.append((det.row, det.side))
        if det.update(np.linalg.inv(origin) @ T):
            origin = None
    truth = list(zip(drive.rows.tolist(), drive.sides.tolist(), strict=True))
    cuts = [i for i in range(1, len(got)) if got[i] != got[i - 1]]
    true_cuts = [i for i in range(1, len(truth)) if truth[i] != truth[i - 1]]
    assert len(cuts) == len(true_cuts) == 5
    assert max(abs(a - b) for a, b in zip(cuts, true_cuts, strict=True)) <= 2
    assert got[-1] == truth[-1] == (3, "back")


def test_a_block_needs_room_for_the_turn_between_rows():
    with pytest.raises(ScenarioError, match="row_spacing_m"):
        load_scenario("block", {"block.row_spacing_m": 2.6})


def test_a_simulated_block_is_one_bag_without_side_topic_and_a_truth_per_row(tmp_path):
    from orchard_mapping.sim.simulate import simulate

    tiny = {"row.n_trees": 1, "block.rows": 2, "camera.rate_hz": 0.5, "path.speed_mps": 1.0, "masks_every": 0,
            "canopy.leaves_per_m3": 1500.0, "fruit.per_tree": [3, 5], "camera.width": 160, "camera.height": 120,
            "camera.fx": 153.75, "camera.fy": 153.75, "camera.cx": 79.5, "camera.cy": 59.5}
    res = simulate(load_scenario("block", tiny), SEED, tmp_path / "sim")
    assert set(res.bags) == {"block"}
    topics = {name for name, _, _ in describe_bag(res.bags["block"]).topics}
    assert TopicsConfig().side not in topics  # the rows and sides come from the camera's turns
    truth = json.loads(res.truth_path.read_text())
    assert truth["schema"] == "orchard_mapping.block_ground_truth/1" and truth["n_rows"] == 2
    stamps = read_rgbd(res.bags["block"]).stamps
    drive = np.asarray(truth["drive"]["trajectory"])
    np.testing.assert_allclose(drive[:, 0], stamps, atol=1e-6)
    for k, row in enumerate(truth["rows"], start=1):
        doc = json.loads((res.out_dir / row["truth"]).read_text())
        assert doc["schema"] == "orchard_mapping.ground_truth/1" and doc["row"] == k
        assert [t["id"] for t in doc["trees"]] == row["tree_ids"] == [k - 1]
        assert (res.out_dir / f"row_{k}" / "tree_surfaces.npz").is_file()
        for side in ("front", "back"):
            s = doc["sides"][side]
            # the side's odom frame is its first camera: the first trajectory pose is the identity
            np.testing.assert_allclose(s["trajectory"][0][1:], [0, 0, 0, 0, 0, 0, 1], atol=1e-6)
            assert s["trajectory"][0][0] == pytest.approx(row["passes"][side]["first_stamp"])
    # `orchard-map inspect` reads the block back: its bag, its rows and each row's truth
    from typer.testing import CliRunner

    from orchard_mapping.cli.main import app

    shown = CliRunner().invoke(app, ["inspect", str(res.out_dir)])
    assert shown.exit_code == 0, shown.output
    assert "Block (scenario block" in shown.output and "row 2: Recordings" in shown.output
