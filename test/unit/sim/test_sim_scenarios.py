"""Scenario files load, build and differ where they say they do; bad scenarios fail with a named key."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.errors import ScenarioError
from orchard_mapping.resources import scenario_dir
from orchard_mapping.sim.render import Renderer
from orchard_mapping.sim.scenario import list_scenarios, load_scenario
from orchard_mapping.sim.scene import Cls, build_scene
from orchard_mapping.sim.simulate import intrinsics_of
from orchard_mapping.sim.trajectory import side_path

SMALL = {"row.n_trees": 3}
SCENARIOS = sorted(p.stem for p in scenario_dir().glob("*.yaml"))


def test_scenario_list_matches_files():
    assert SCENARIOS and list_scenarios() == SCENARIOS
    assert "standard" in SCENARIOS


@pytest.mark.parametrize("name", SCENARIOS)
def test_scenario_loads_and_builds(name):
    sc = load_scenario(name, SMALL)
    assert sc.name == name and sc.description
    scene = build_scene(sc, 0)
    assert len(scene.trees) == 3 * sc.block.rows  # a block: each row its own trees
    n_tri = len(scene.triangles)
    assert len(scene.tri_cls) == len(scene.tri_inst) == len(scene.tri_albedo) == n_tri
    assert scene.triangles.min() >= 0 and scene.triangles.max() < len(scene.vertices)
    assert np.isfinite(scene.vertices).all()
    present = set(np.unique(scene.tri_cls).tolist())
    assert {Cls.GROUND, Cls.TRUNK, Cls.BRANCH, Cls.LEAF, Cls.FRUIT, Cls.POST, Cls.WIRE, Cls.HEDGE} <= present
    # Every tree owns its trunk triangles and every fruit its sphere.
    for tree in scene.trees:
        t0, t1 = tree.trunk_tri
        assert np.all(scene.tri_cls[t0:t1] == Cls.TRUNK) and np.all(scene.tri_inst[t0:t1] == tree.id)
    fruit_inst = scene.tri_inst[scene.tri_cls == Cls.FRUIT]
    assert set(np.unique(fruit_inst).tolist()) == set(range(len(scene.fruit)))


def test_slope_weeds_has_more_weeds_and_steeper_ground():
    std = build_scene(load_scenario("standard", SMALL), 0)
    sw = build_scene(load_scenario("slope_weeds", SMALL), 0)
    n_std = int(np.sum(std.tri_cls == Cls.WEED))
    n_sw = int(np.sum(sw.tri_cls == Cls.WEED))
    assert n_sw > 5 * n_std > 0  # 60 vs 6 clumps per m^2
    assert sw.terrain.slope > std.terrain.slope


def test_young_row_has_thin_trunks_and_small_crowns():
    """A young row's trunks are 18-36 mm at the diameter height (standard: 40-90 mm) and its trees lower."""
    young = build_scene(load_scenario("young", {"row.n_trees": 8}), 0)
    std = build_scene(load_scenario("standard", {"row.n_trees": 8}), 0)

    def diameters(scene):  # (T,) m, 0.3 m up the trunk (the axis is within a few degrees of vertical)
        return np.array([np.interp(0.30, t.axis_s, t.axis_diam) for t in scene.trees])

    def heights(scene):  # (T,) m above the local ground
        return np.array([(t.top_z_point - t.ground_point) @ t.ground_normal for t in scene.trees])

    d_young, d_std = diameters(young), diameters(std)
    assert np.all((d_young > 0.015) & (d_young < 0.04)), d_young
    assert d_young.max() < d_std.min(), (d_young, d_std)
    assert heights(young).max() < heights(std).max(), (heights(young), heights(std))


@pytest.mark.parametrize("direction, back_sign", [("return", -1.0), ("same", 1.0)])
def test_back_side_walked_round_the_row_or_the_same_way(direction, back_sign):
    """The level sweep of the front side moves towards +x; the back side's towards -x (round the row) or,
    with path.back_direction "same", towards +x too; either way it still looks at the row (-y)."""
    sc = load_scenario("standard", {**SMALL, "path.back_direction": direction})
    scene = build_scene(sc, 0)
    for side, sign, look in (("front", 1.0, 1.0), ("back", back_sign, -1.0)):
        path = side_path(sc, side, scene.row_x, scene.terrain, np.random.default_rng(0), 0.0)
        x = path.poses[:, 0, 3]
        half = len(x) // 3  # within the level sweep
        assert np.sign(x[half] - x[0]) == sign, (side, direction)
        assert np.sign(path.poses[half, 1, 2]) == look  # optical axis (z) across the row, towards it


def test_partial_overlap_side_spans_differ():
    sc = load_scenario("partial_overlap", SMALL)
    scene = build_scene(sc, 0)
    rng = np.random.default_rng(0)
    xs = {side: side_path(sc, side, scene.row_x, scene.terrain, rng, 0.0).poses[:, 0, 3] for side in ("front", "back")}
    lo = scene.row_x[0] - sc.row.margin_m
    span = scene.row_x[1] + sc.row.margin_m - lo
    jit = 0.06  # 12 mm RMS hand-held position jitter, peaks ~3x
    # front covers 0-70 % of the row, back 30-100 %.
    assert xs["front"].min() == pytest.approx(lo, abs=jit)
    assert xs["front"].max() == pytest.approx(lo + 0.7 * span, abs=jit)
    assert xs["back"].min() == pytest.approx(lo + 0.3 * span, abs=jit)
    assert xs["back"].max() == pytest.approx(lo + span, abs=jit)


def test_wind_moves_leaves_not_trunks(half_res):
    """Two renders of one pose at different times: many leaf pixels change, trunk pixels (almost) never."""
    sc = load_scenario("wind", {**SMALL, **half_res})
    scene = build_scene(sc, 0)
    renderer = Renderer(scene, intrinsics_of(sc), 0)
    path = side_path(sc, "front", scene.row_x, scene.terrain, np.random.default_rng(0), 0.0)
    # A level-sweep pose facing the middle tree sees its trunk and the lower canopy.
    x_mid = scene.trees[1].base[0]
    level = np.flatnonzero(np.abs(path.poses[:, 2, 2]) < 0.1)
    T = path.poses[level[np.argmin(np.abs(path.poses[level, 0, 3] - x_mid))]]
    a, b = renderer.render(T, 0.0), renderer.render(T, 0.31)
    leaf = (a.cls == Cls.LEAF) | (b.cls == Cls.LEAF)
    trunk = (a.cls == Cls.TRUNK) & (b.cls == Cls.TRUNK) & (a.inst == b.inst)
    assert leaf.sum() > 2000 and trunk.sum() > 50
    leaf_changed = np.mean((a.tri != b.tri)[leaf] | (np.abs(a.depth - b.depth)[leaf] > 0.005))
    assert leaf_changed > 0.3
    # Trunks are rigid: where both renders see the same trunk the depth is the same.
    assert np.mean(np.abs(a.depth - b.depth)[trunk] > 1e-4) < 0.01
    # Without wind, time changes nothing.
    calm = Renderer(build_scene(load_scenario("standard", {**SMALL, **half_res}), 0), intrinsics_of(sc), 0)
    c, d = calm.render(T, 0.0), calm.render(T, 0.31)
    assert np.array_equal(c.depth, d.depth) and np.array_equal(c.tri, d.tri)


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        ({"camera.bogus_key": 1}, "camera.bogus_key"),
        ({"path.mode": "zigzag"}, "path.mode"),
        ({"row.n_trees": 0}, "row.n_trees"),
        ({"trunk.diameter_mean_m": 0.2}, "diameter_mean_m"),
        ({"path.front_span": [0.8, 0.2]}, "front_span"),
    ],
)
def test_bad_scenario_key_names_the_key(overrides, key):
    with pytest.raises(ScenarioError, match=key.replace(".", r"\.")):
        load_scenario("standard", overrides)


def test_bad_scenario_file_and_name(tmp_path):
    bad = tmp_path / "mine.yaml"
    bad.write_text("row:\n  n_tree: 3\n")
    with pytest.raises(ScenarioError, match=r"row\.n_tree") as err:
        load_scenario(bad)
    assert str(bad) in str(err.value)
    with pytest.raises(ScenarioError, match="unknown scenario 'no_such'.*standard"):
        load_scenario("no_such")
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    with pytest.raises(ScenarioError, match="mapping"):
        load_scenario(tmp_path / "list.yaml")
