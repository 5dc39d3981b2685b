"""The unseen domain's point-splatting renderer, its truth fits and its recordings (sim/splat.py,
sim/scan_rows.py), on small synthetic point sets (not the committed scans)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.sim.scan_row_scene import (
    ScanDataError,
    ScanRowSpec,
    build_scan_row,
    fit_circle,
    load_scan_trees,
    trunk_slices,
)
from orchard_mapping.sim.scan_rows import generate_scan_row
from orchard_mapping.sim.splat import PCls, PointScene, SplatRenderer, StereoSensor

K = CameraIntrinsics(160, 120, 150.0, 150.0, 79.5, 59.5)


def _wall(depth: float, spacing: float, half: float = 3.0) -> PointScene:
    g = np.arange(-half, half, spacing)
    x, y = np.meshgrid(g, g)
    n = x.size
    xyz = np.column_stack([x.ravel(), y.ravel(), np.full(n, depth)])
    return PointScene(xyz.astype(np.float32), np.full(n, spacing, np.float32), np.full((n, 3), 0.5, np.float32),
                      np.tile(np.float32([0, 0, -1]), (n, 1)), np.full(n, PCls.GROUND, np.uint8),
                      np.full(n, 7, np.int32))


def test_flat_wall_at_its_depth_without_holes():
    # Spacing 1.5 px at 2 m (fx 150: 1 px = 13.3 mm), splat radius = spacing: the wall fills every pixel.
    spacing = 0.02
    r = SplatRenderer(_wall(2.0, spacing), K)
    f = r.render(np.eye(4))  # camera at the origin looking along +z (the wall's normal)
    assert (f.depth > 0).all()
    np.testing.assert_allclose(f.depth, 2.0, atol=1e-5)
    assert (f.cls == PCls.GROUND).all() and (f.inst == 7).all() and (f.index >= 0).all()
    # Each pixel's point is the one nearest to its ray (within one splat radius).
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    ray_x = (u - K.cx) / K.fx * 2.0
    assert np.abs(f.points[..., 0] - ray_x).max() <= spacing + 1e-6


def test_nearer_points_win_and_sparse_points_leave_holes():
    near = _wall(1.0, 0.01, half=0.2)
    far = _wall(3.0, 0.03)
    both = PointScene(*(np.concatenate([getattr(near, k), getattr(far, k)]) for k in
                        ("xyz", "radius", "albedo", "normal", "cls", "inst")))
    f = SplatRenderer(both, K).render(np.eye(4))
    assert np.isclose(f.depth[int(K.cy), int(K.cx)], 1.0, atol=1e-5)
    assert np.isclose(f.depth[2, 2], 3.0, atol=1e-5)
    thin = _wall(2.0, 0.05)
    thin = replace(thin, radius=np.full(len(thin.xyz), 0.003, np.float32))  # 0.2 px: single pixels
    f = SplatRenderer(thin, K).render(np.eye(4))
    assert 0.0 < (f.depth > 0).mean() < 0.5


def test_stereo_sensor_noise_grows_with_range():
    s = StereoSensor(low_texture=0.0, speckle=0.0, edge_hole=0.0, flying=0.0)
    rng = np.random.default_rng(0)
    sds = []
    for z in (1.0, 3.0):
        f = SplatRenderer(_wall(z, 0.03 * z), K).render(np.eye(4))
        _, d = s.apply(f, K.fx, rng)
        assert (d > 0).mean() > 0.99
        sds.append(float(np.std(d[d > 0] - z)))
    assert sds[1] > 5 * sds[0]  # ~z^2
    assert sds[0] == pytest.approx(s.depth_sd(1.0, K.fx), rel=0.5)


def test_circle_fit_recovers_a_cylinder_diameter():
    rng = np.random.default_rng(3)
    c = np.array([0.31, -0.12])
    th = rng.uniform(0, 2 * np.pi, 400)
    xy = c + 0.025 * np.column_stack([np.cos(th), np.sin(th)])
    centre, r = fit_circle(xy)
    assert abs(2 * r - 0.05) < 1e-9 and np.allclose(centre, c)
    # A leaning cylinder of 52 mm sampled with 0.1 mm noise: the sliced fit within 0.2 mm.
    axis = np.array([0.05, -0.03, 1.0])
    axis /= np.linalg.norm(axis)
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    n = 20000
    th = rng.uniform(0, 2 * np.pi, n)
    h = rng.uniform(0, 1.0, n)
    base = np.array([1.0, 2.0, 0.1])
    pts = (base + h[:, None] * axis + 0.026 * (np.cos(th)[:, None] * e1 + np.sin(th)[:, None] * e2)
           + rng.normal(0, 0.0001, (n, 3)))
    sl = trunk_slices(pts, base + np.array([0.01, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.03,
                      np.arange(0.1, 0.9, 0.05))
    assert np.abs(2 * sl.radii - 0.052).max() < 0.0002
    assert np.degrees(np.arccos(abs(sl.axis @ axis))) < 0.1


def _synthetic_scan(rng: np.random.Generator, trunk_r: float) -> dict:
    """A 20 m 'tree' in scan scale: a cylinder trunk to 8 m and a cone of foliage points above it."""
    n_t = 12000
    th = rng.uniform(0, 2 * np.pi, n_t)
    z = rng.uniform(0, 10, n_t)
    trunk = np.column_stack([trunk_r * np.cos(th), trunk_r * np.sin(th), z])
    n_f = 6000
    zf = rng.uniform(8, 20, n_f)
    rf = rng.uniform(0, 1, n_f) * (20 - zf) / 12 * 2.0
    af = rng.uniform(0, 2 * np.pi, n_f)
    fol = np.column_stack([rf * np.cos(af), rf * np.sin(af), zf])
    pts = np.vstack([trunk, fol])
    axis = np.column_stack([np.zeros(19), np.zeros(19), np.arange(0.6, 8.0, 0.4)])
    return {"points": np.round(pts * 1000).astype(np.int16), "axis": axis.astype(np.float32),
            "source": np.array("synthetic")}


def test_missing_scans_raise_a_typed_error(tmp_path):
    with pytest.raises(ScanDataError, match="no real-tree scans"):
        load_scan_trees(tmp_path)


def _tiny_row(tmp_path) -> ScanRowSpec:
    """Two synthetic scans under tmp_path/scans and the spec of a tiny, fast row of them."""
    data = tmp_path / "scans" / "synthetic"
    data.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for k, r in enumerate((0.18, 0.22)):
        np.savez_compressed(data / f"tree{k}.npz", **_synthetic_scan(rng, r))
    return ScanRowSpec(n_trees=2, rate_hz=1.0, width=160, height=120, fx=152.0, fy=152.0, cx=80.0, cy=60.0,
                       background_row_m=0.0, ground_spacing_m=0.04, margin_m=0.5)


def test_tiny_scan_row_writes_readable_bags(tmp_path):
    spec = _tiny_row(tmp_path)
    res = generate_scan_row(tmp_path / "row", seed=1, spec=spec, data_dir=tmp_path / "scans")
    truth = json.loads(res.truth_path.read_text())
    assert truth["schema"] == "orchard_mapping.ground_truth/1" and len(truth["trees"]) == 2
    radius = {"tree0": 0.18, "tree1": 0.22}
    for t in truth["trees"]:
        # the truth diameter from the scan's own points: the synthetic cylinder's, scaled to the row
        assert t["trunk"]["diameter_m"] == pytest.approx(2 * radius[t["scan"]] * t["scale"], abs=3e-4)
        assert 2.0 <= t["height_m"] <= 2.9
        assert set(t["observed"]) == {"front", "back"}
    for side in ("front", "back"):
        seq = read_rgbd(res.bags[side])
        assert len(seq) == res.frames[side]
        frame = next(iter(seq))
        assert frame.color.shape == (120, 160, 3) and frame.depth.shape == (120, 160)
        assert (frame.depth > 0).mean() > 0.2
        assert seq.intrinsics.fx == pytest.approx(152.0)


def test_fruit_in_a_scan_row_hang_in_the_crowns_and_are_seen(tmp_path):
    """ScanRowSpec.fruit_per_tree hangs fruit in the crowns' outer shell: inside the tree's height, above its
    clear trunk, none interpenetrating; the truth lists each with its visibility per side and the counts add
    up; the fruit draws leave the rest of the row as it was without fruit (trees, trunk truth, ground)."""
    spec = _tiny_row(tmp_path)
    trees = load_scan_trees(tmp_path / "scans")
    plain = build_scan_row(1, spec, trees)
    fruity = build_scan_row(1, replace(spec, fruit_per_tree=(8, 12)), trees)
    assert not plain.fruit and 16 <= len(fruity.fruit) <= 24
    for a, b in zip(plain.trees, fruity.trees, strict=True):
        assert np.array_equal(a.base, b.base) and a.height == b.height and np.array_equal(a.slices.radii, b.slices.radii)
        assert len(b.points) < len(a.points)  # the crown's points inside a fruit went
    pos = np.array([f.position for f in fruity.fruit])
    rad = np.array([f.radius for f in fruity.fruit])
    gap = np.linalg.norm(pos[:, None] - pos[None], axis=2) - rad[:, None] - rad[None]
    assert gap[~np.eye(len(rad), dtype=bool)].min() > 0.004
    for f in fruity.fruit:
        t = fruity.trees[f.tree]
        h = (f.position - t.ground_point) @ t.ground_normal
        assert t.clear_height < h < t.height and 0.033 <= f.radius <= 0.045
    on = fruity.points.cls == PCls.FRUIT
    assert set(np.unique(fruity.points.inst[on])) == set(range(len(fruity.fruit)))

    res = generate_scan_row(tmp_path / "row", seed=1, spec=replace(spec, fruit_per_tree=(8, 12)),
                            data_dir=tmp_path / "scans")
    truth = json.loads(res.truth_path.read_text())
    listed = [f for t in truth["trees"] for f in t["fruit"]]
    assert len(listed) == len(fruity.fruit)
    for t in truth["trees"]:
        v = t["fruit_visible"]
        assert t["fruit_count"] == len(t["fruit"])
        assert v["either"] == sum(f["visible"]["front"] or f["visible"]["back"] for f in t["fruit"])
        assert v["both"] <= min(v["front"], v["back"]) <= max(v["front"], v["back"]) <= v["either"]
    assert sum(t["fruit_visible"]["either"] for t in truth["trees"]) >= len(listed) // 3  # crowns' outer shell
