"""Trait definitions of the ground truth, recomputed from the scene description (build_scene)."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.scene import Cls, build_scene, local_ground_plane
from orchard_mapping.sim.truth import (
    alpha_complex_volume,
    diameter_at_height,
    tree_height,
)

N_BIG = 200


@pytest.fixture(scope="module")
def big_row():
    """A 200-tree row (scene only, no rendering). Fruit and weeds are cut to make it cheap to build;
    trunks and canopies (which define diameters and heights) keep their standard settings."""
    sc = load_scenario("standard", {"row.n_trees": N_BIG, "fruit.per_tree": [1, 2], "structure.weeds_per_m2": 0.0})
    return build_scene(sc, 11)


def _tree_vertices(scene, tree) -> np.ndarray:
    """All mesh vertices of one tree: trunk, branches, leaves and its fruit. (M, 3)"""
    own = np.isin(scene.tri_cls, [Cls.TRUNK, Cls.BRANCH, Cls.LEAF]) & (scene.tri_inst == tree.id)
    own |= (scene.tri_cls == Cls.FRUIT) & np.isin(scene.tri_inst, tree.fruit_index)
    return scene.vertices[np.unique(scene.triangles[own])]


def test_height_is_top_of_geometry_above_local_ground(standard_sim):
    """height_m = highest vertex of the tree's mesh above its local ground plane (0.5 m least squares)."""
    scene = standard_sim.scene
    for tree, t in zip(scene.trees, standard_sim.truth["trees"], strict=True):
        gp, gn = local_ground_plane(scene.terrain, float(tree.base[0]), float(tree.base[1]), radius=0.5)
        np.testing.assert_allclose(t["local_ground"]["point"], gp, atol=2e-5)
        np.testing.assert_allclose(t["local_ground"]["normal"], gn, atol=2e-6)
        top = float(np.max((_tree_vertices(scene, tree) - gp) @ gn))
        assert t["height_m"] == pytest.approx(top, abs=1e-4)  # JSON rounds to 0.1 mm
        # The truth's position is the trunk axis where it meets the local ground plane, near the scene's base.
        pos = np.asarray(t["position"])
        assert (pos - gp) @ gn == pytest.approx(0.0, abs=1e-4)
        assert np.linalg.norm(pos - tree.base) < 0.05


def test_diameter_is_axis_interpolation_and_mesh(standard_sim):
    """diameter_m = TreeGeom.axis_diam interpolated at diameter height, and the trunk mesh has that diameter."""
    scene = standard_sim.scene
    dh = standard_sim.truth["diameter_height_m"]
    for tree, t in zip(scene.trees, standard_sim.truth["trees"], strict=True):
        h_axis = (tree.axis_points - tree.ground_point) @ tree.ground_normal
        s_dh = np.interp(dh, h_axis, tree.axis_s)  # arc length at diameter height
        d = float(np.interp(s_dh, tree.axis_s, tree.axis_diam))
        assert t["trunk"]["diameter_m"] == pytest.approx(d, abs=2e-5)
        # Mesh: trunk vertices within 3 cm of diameter height lie at d/2 from the axis (taper 1.2 cm/m: < 0.1 mm).
        a0 = np.array([np.interp(s_dh, tree.axis_s, tree.axis_points[:, k]) for k in range(3)])
        k = int(np.searchsorted(tree.axis_s, s_dh))
        w = tree.axis_points[k + 1] - tree.axis_points[k - 1]
        w /= np.linalg.norm(w)
        v = scene.vertices[np.unique(scene.triangles[tree.trunk_tri[0]:tree.trunk_tri[1]])] - a0
        near = np.abs(v @ w) < 0.03
        assert near.sum() >= 40
        radial = np.linalg.norm(v[near] - np.outer(v[near] @ w, w), axis=1)
        assert 2 * np.median(radial) == pytest.approx(d, abs=5e-4)


def test_an_elliptical_trunk_keeps_its_stated_diameter_as_the_mean_of_its_axes():
    """trunk.ellipticity e: the cross-section's axes are d (1 + e) and d (1 - e) (two caliper readings at right
    angles average to the stated d); bark_roughness_m adds bumps of that sd. The cross-section draws from a
    stream of its own: with or without either, the rest of the row is the same (trees compare one by one)."""
    over = {"row.n_trees": 3, "fruit.per_tree": [1, 2], "structure.weeds_per_m2": 0.0}
    plain = build_scene(load_scenario("standard", over), 5)
    assert build_scene(load_scenario("standard", {**over, "trunk.ellipticity": [0.0, 0.0]}), 5).trees[1].axis_diam \
        .tolist() == plain.trees[1].axis_diam.tolist()

    def rings(scene):  # per tree: (radii of the mesh ring near the diameter height (20,), stated diameter)
        for tree in scene.trees:
            k = int(np.searchsorted(tree.axis_s, 0.3))
            w = tree.axis_points[k + 1] - tree.axis_points[k - 1]
            w /= np.linalg.norm(w)
            v = scene.vertices[np.unique(scene.triangles[tree.trunk_tri[0]:tree.trunk_tri[1]])] - tree.axis_points[k]
            ring = v[np.abs(v @ w) < 1e-6]
            assert len(ring) == 20
            yield np.linalg.norm(ring - np.outer(ring @ w, w), axis=1), tree.axis_diam[k]

    oval = build_scene(load_scenario("standard", {**over, "trunk.ellipticity": [0.08, 0.08],
                                                  "trunk.bark_roughness_m": 0.002}), 5)
    for a, b in zip(plain.trees, oval.trees, strict=True):
        assert a.axis_diam.tolist() == b.axis_diam.tolist() and a.top_z_point.tolist() == b.top_z_point.tolist()
        assert a.canopy_points.shape == b.canopy_points.shape and np.array_equal(a.canopy_points, b.canopy_points)
    for radial, d in rings(build_scene(load_scenario("standard", {**over, "trunk.ellipticity": [0.08, 0.08]}), 5)):
        assert radial.max() == pytest.approx(0.54 * d, rel=0.01)  # a vertex lies within 9 deg of each axis
        assert radial.min() == pytest.approx(0.46 * d, rel=0.01)
    bumps = [radial - d / 2 for radial, d in rings(
        build_scene(load_scenario("standard", {**over, "trunk.bark_roughness_m": 0.002}), 5))]
    assert 0.001 < np.std(bumps) < 0.003


def test_trunk_diameter_distribution(big_row):
    """Over 200 trees: mean ~0.069 m, sd ~0.0085 m, all in [0.04, 0.09] m.

    Sampling error with n = 200: se(mean) = 0.0085 / sqrt(200) = 0.0006 m, se(sd) ~ 0.0085 / sqrt(400)
    = 0.0004 m; clipping at 0.04 / 0.09 (-3.4 / +2.5 sd) moves both by < 0.0002 m. Allow ~3.5 se.
    """
    d = np.array([diameter_at_height(t, 0.30) for t in big_row.trees])
    assert len(d) == N_BIG
    assert d.mean() == pytest.approx(0.069, abs=0.0022)
    assert d.std(ddof=1) == pytest.approx(0.0085, abs=0.0015)
    assert d.min() >= 0.04 - 1e-9 and d.max() <= 0.09 + 1e-9


def test_tree_heights(big_row):
    """Heights in the design's 1.9-2.6 m, with an allowance at the bottom.

    A tree's drawn height is the top of its canopy envelope; the top leaves are kept only where their centre
    is at least 3 cm below it and inside the narrowing envelope tip, and a leaf's tip reaches at most 4 cm
    above its centre. So the highest point lies from a few cm to ~0.1 m under the drawn height (at most 1 cm
    over it).
    """
    h = np.array([tree_height(t) for t in big_row.trees])
    assert h.min() >= 1.9 - 0.12
    assert h.max() <= 2.6 + 0.01
    # Spread over the whole range (uniform 1.9-2.6: mean 2.25, sd 0.2).
    assert np.mean(h) == pytest.approx(2.25 - 0.04, abs=0.06)
    assert np.std(h) == pytest.approx(0.7 / np.sqrt(12), abs=0.04)


def _cube_samples(rng: np.random.Generator, lo: np.ndarray, size: float, n_edge: int = 21,
                  n_inner: int = 3000) -> np.ndarray:
    """Points on a cube's faces (n_edge x n_edge grid per face) and uniform inside it. (N, 3)"""
    g = np.linspace(0, size, n_edge)
    A, B = np.meshgrid(g, g)
    a, b = A.ravel(), B.ravel()
    z, o = np.zeros_like(a), np.full_like(a, size)
    faces = [np.stack(f, 1) for f in ((a, b, z), (a, b, o), (a, z, b), (a, o, b), (z, a, b), (o, a, b))]
    # Tiny jitter so that the grid's co-spherical points do not make a degenerate Delaunay.
    surf = np.vstack(faces) + rng.normal(0, 1e-4 * size, (6 * len(a), 3))
    surf = np.clip(surf, 0, size)
    inner = rng.uniform(0, size, (n_inner, 3))
    return lo + np.vstack([surf, inner])


def test_alpha_complex_volume_cube():
    """A unit cube densely sampled (surface + interior): volume 1 within 2 %."""
    rng = np.random.default_rng(0)
    pts = _cube_samples(rng, np.zeros(3), 1.0)
    assert alpha_complex_volume(pts, alpha_m=0.3) == pytest.approx(1.0, rel=0.02)


def test_alpha_complex_volume_sphere():
    """A sphere of radius 0.5 (Fibonacci surface + uniform interior): 4/3 pi r^3 within 3 %.

    With 3000 surface points the inscribed polyhedron misses < 0.5 % of the volume.
    """
    rng = np.random.default_rng(1)
    r, n = 0.5, 3000
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    th = np.pi * (1 + 5**0.5) * k
    surf = r * np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)
    d = rng.normal(size=(4000, 3))
    inner = d / np.linalg.norm(d, axis=1, keepdims=True) * (r * rng.uniform(0, 1, (4000, 1)) ** (1 / 3))
    vol = alpha_complex_volume(np.vstack([surf, inner]) + [3.0, -1.0, 2.0], alpha_m=0.2)
    assert vol == pytest.approx(4 / 3 * np.pi * r**3, rel=0.03)


def test_alpha_complex_is_not_the_convex_hull():
    """Two unit cubes 0.6 m apart: the alpha complex (alpha 0.25) bridges nothing; alpha 10 gives the hull."""
    rng = np.random.default_rng(2)
    pts = np.vstack([_cube_samples(rng, np.zeros(3), 1.0, 13, 600),
                     _cube_samples(rng, np.array([1.6, 0.0, 0.0]), 1.0, 13, 600)])
    assert alpha_complex_volume(pts, alpha_m=0.25) == pytest.approx(2.0, rel=0.02)
    assert alpha_complex_volume(pts, alpha_m=10.0) == pytest.approx(2.6, rel=0.02)


def test_trunk_radii_takes_the_scenarios_trunk_spec_by_its_annotated_type():
    """trunk_radii's annotations resolve (they named TrunkSpec, which scene.py did not import: get_type_hints
    raised NameError), and the function gives a round trunk as is and an elliptical one as (K, segments)."""
    import typing

    from orchard_mapping.sim import scene as scene_module
    from orchard_mapping.sim.scenario import TrunkSpec

    assert typing.get_type_hints(scene_module.trunk_radii)["tr"] is TrunkSpec
    s = np.linspace(0.0, 1.0, 5)
    r_mean = np.full(5, 0.04)
    plain = load_scenario("standard", {"trunk.ellipticity": [0.0, 0.0], "trunk.bark_roughness_m": 0.0}).trunk
    assert isinstance(plain, TrunkSpec)
    assert scene_module.trunk_radii(np.random.default_rng(0), plain, s, r_mean, 20) is r_mean
    oval = load_scenario("standard", {"trunk.ellipticity": [0.08, 0.08]}).trunk
    radii = scene_module.trunk_radii(np.random.default_rng(0), oval, s, r_mean, 20)
    assert radii.shape == (5, 20)
    assert radii.max() == pytest.approx(0.04 * 1.08, rel=0.02)


def test_surface_samples_name_each_tree_and_cover_its_surface(big_row):
    """tree_surface_samples: every tree's mesh vertex lies on a sample of that tree; posts and ground are -1 and
    sampled densely enough (<= 3 cm apart on a post) that no point of them is nearer a leaf corner."""
    from scipy.spatial import cKDTree

    from orchard_mapping.sim.truth import SURFACE_SAMPLE_M, tree_surface_samples

    pts, tree = tree_surface_samples(big_row)
    assert pts.dtype == np.float32 and tree.shape == (len(pts),)
    assert set(np.unique(tree).tolist()) == {-1, *range(N_BIG)}
    kd = cKDTree(pts)
    for t in big_row.trees[:3]:
        v = _tree_vertices(big_row, t)
        d, k = kd.query(v)
        assert np.all(d < 1e-5) and np.all(tree[k] == t.id)
    post = big_row.vertices[np.unique(big_row.triangles[big_row.tri_cls == Cls.POST])]
    _, k = kd.query(post)
    assert np.all(tree[k] == -1)
    # along a post's height (long triangles) samples are no farther apart than ~SURFACE_SAMPLE_M
    pp = pts[tree == -1]
    p0 = post[0]
    near = pp[np.linalg.norm(pp[:, :2] - p0[:2], axis=1) < 0.08]
    gaps = np.diff(np.sort(near[:, 2]))
    assert len(near) > 50 and gaps.max() < 2 * SURFACE_SAMPLE_M
