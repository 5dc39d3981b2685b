"""Domain randomisation of the detector's training scenes (orchard_mapping.sim.domain)."""

import json

import numpy as np
import pytest

from orchard_mapping.sim.domain import random_domain, wide_domain
from orchard_mapping.sim.scenario import load_scenario


@pytest.mark.parametrize("seed", range(5))
def test_wide_draws_leave_the_narrow_draws_of_a_seed_as_they_were(seed):
    # the training sets simulated before the wide looks existed must come out of the same commands again
    narrow = random_domain(np.random.default_rng([seed, 3]))
    wide = random_domain(np.random.default_rng([seed, 3]), wide=True)
    overridable = set().union(*(wide_domain(np.random.default_rng(k)) for k in range(200)))
    assert {"appearance.bark_rgb", "canopy.leaves_per_m3", "camera.width"} <= overridable
    for key, value in narrow.items():
        assert wide[key] == value or key in overridable, key
    assert sum(wide[k] != narrow.get(k) for k in wide) >= 4  # and the wide look is another look


def test_wide_draws_give_valid_scenarios_and_cover_what_real_orchards_show():
    looks = [random_domain(np.random.default_rng([7, k]), wide=True) for k in range(300)]
    for over in looks[:40]:
        load_scenario("standard", over)  # every draw is a scenario the simulator accepts
    bark = np.array([o["appearance.bark_rgb"] for o in looks])  # (300, 3)
    lightness = bark.mean(axis=1)
    assert (lightness > 0.75).mean() > 0.05  # whitewashed trunks
    assert ((lightness > 0.45) & (lightness < 0.75)).mean() > 0.2  # young light-grey bark
    assert (lightness < 0.2).mean() > 0.05  # old dark bark
    leaves = np.array([o["canopy.leaves_per_m3"] for o in looks])
    assert 0.15 < (leaves < 200).mean() < 0.35  # dormant rows, and no fruit on them
    assert all(o["fruit.per_tree"] == [0, 0] for o in looks if o["canopy.leaves_per_m3"] < 200)
    distance = np.array([o["path.distance_m"] for o in looks])
    assert distance.min() < 0.7 and distance.max() > 2.3
    wide_frames = [o for o in looks if o.get("camera.width") == 1280]
    assert 0.2 < len(wide_frames) / len(looks) < 0.4
    assert all(o["camera.height"] == 720 and abs(o["camera.cx"] - 639.5) < 1e-9 for o in wide_frames)
    hedge = np.array([o["structure.hedge_height_m"] for o in looks])
    assert (hedge < 1.2).mean() > 0.1  # low neighbouring rows: sky behind the trunks


def test_a_low_hedge_is_built_to_its_height():
    from orchard_mapping.sim.scene import Cls, build_scene

    heights = {}
    for h in (0.9, 2.7):
        sc = load_scenario("standard", {"row.n_trees": 1, "structure.hedge_height_m": h})
        scene = build_scene(sc, 0)
        hedge = scene.vertices[np.unique(scene.triangles[scene.tri_cls == Cls.HEDGE])]
        heights[h] = float(np.percentile(hedge[:, 2] - scene.terrain.height(hedge[:, 0], hedge[:, 1]), 99))
    assert heights[0.9] < 0.95 and heights[2.7] > 2.4


def test_a_row_with_fewer_fruit_than_trees_is_simulated(tmp_path):
    # dormant rows draw no fruit or a few: the truth looked fruit up for every pixel's instance, so a row
    # with fewer fruit than trees indexed past the fruit table
    from orchard_mapping.sim.simulate import simulate

    over = {"row.n_trees": 3, "fruit.per_tree": [0, 1], "canopy.leaves_per_m3": 50.0, "camera.rate_hz": 1.0,
            "camera.width": 160, "camera.height": 120, "camera.fx": 153.75, "camera.fy": 153.75,
            "camera.cx": 79.5, "camera.cy": 59.5, "path.mode": "single_pass"}
    sim = simulate(load_scenario("standard", over), 3, tmp_path / "row")
    truth = json.loads((sim.out_dir / "ground_truth.json").read_text())
    assert len(truth["trees"]) == 3 and sum(len(t["fruit"]) for t in truth["trees"]) <= 3


def test_the_varied_fruit_look_changes_the_fruit_colours_and_nothing_else():
    """fruit.look: varied draws the fruit's colours from a stream of its own: the scene's geometry, classes,
    fruit and every other triangle's colour stay those of the plain look; the fruit get a ground colour and a
    blush (red fruit mostly blushed, green fruit mostly not), and two fruit are never one colour."""
    from orchard_mapping.sim.scene import Cls, build_scene

    for seed in (3, 8):
        over = {"row.n_trees": 2, "fruit.red_fraction": 0.6}
        plain = build_scene(load_scenario("standard", over), seed)
        varied = build_scene(load_scenario("standard", over | {"fruit.look": "varied"}), seed)
        assert np.array_equal(plain.vertices, varied.vertices)
        assert np.array_equal(plain.tri_cls, varied.tri_cls) and np.array_equal(plain.tri_inst, varied.tri_inst)
        assert [(f.position.tolist(), f.radius, f.color) for f in plain.fruit] == \
            [(f.position.tolist(), f.radius, f.color) for f in varied.fruit]
        fruit = plain.tri_cls == Cls.FRUIT
        assert fruit.sum() > 1000
        assert np.array_equal(plain.tri_albedo[~fruit], varied.tri_albedo[~fruit])
        alb = varied.tri_albedo[fruit]  # (T, 3)
        inst = varied.tri_inst[fruit]
        redness = alb[:, 0] - alb[:, 1]  # > 0 blushed, < 0 green or golden ground
        per_fruit = {k: redness[inst == k] for k in np.unique(inst)}
        red = [varied.fruit[k].color == "red" for k in per_fruit]
        blushed = np.array([(r > 0.15).mean() for r in per_fruit.values()])
        assert np.mean(blushed[red]) > 0.4 and np.mean(blushed[~np.array(red)]) < 0.15
        assert np.mean([(r > 0.15).any() and (r < 0.0).any() for r in per_fruit.values()]) > 0.3  # two-tone fruit
        means = np.array([alb[inst == k].mean(axis=0) for k in per_fruit])
        assert len(np.unique(means.round(3), axis=0)) == len(means)
        # the plain look: one colour per fruit, saturated red or green
        assert all(len(np.unique(plain.tri_albedo[fruit][plain.tri_inst[fruit] == k], axis=0)) == 1 for k in per_fruit)
