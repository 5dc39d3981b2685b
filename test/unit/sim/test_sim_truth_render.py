"""Ground truth agrees with the recording it describes, read back from the bags and masks on disk.

Tolerances come from the sensor model (orchard_mapping/sim/render.py::SensorModel):
depth noise is Gaussian with sd = depth_sigma_coeff * z^2 (about 7 mm at 1.3 m),
the bag stores depth as 16UC1 millimetres (+-0.5 mm rounding), and the trunk
mesh is a 20-sided polygon inscribed in the true circle (the flat faces lie up
to r * (1 - cos(pi / 20)) ~ 0.5 mm inside it). Depth edges carry flying pixels
and holes, so depth is only compared where the instance mask shows the same
trunk over the whole 3x3 neighbourhood (no depth edge can touch the pixel).
"""

from __future__ import annotations

import numpy as np

from orchard_mapping.sim.simulate import MASK_FRUIT, MASK_POST, MASK_TRUNK
from orchard_mapping.sim.truth import FRUIT_MIN_PIXELS, FRUIT_MIN_VISIBLE_FRACTION

SIDES = ("front", "back")
QUANT_M = 0.0005  # 16UC1 stores rounded millimetres
GEOM_M = 0.001  # inscribed 20-gon (<= 0.55 mm for r <= 45 mm) + taper/lean over the ~1 cm the hit lies off dh


def _axis_at_height(tree, h: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Scene trunk axis point (3,) and unit direction (3,) at height h above the local ground, and the radius."""
    hs = (tree.axis_points - tree.ground_point) @ tree.ground_normal  # (K,)
    p = np.array([np.interp(h, hs, tree.axis_points[:, k]) for k in range(3)])
    k = int(np.clip(np.searchsorted(hs, h), 1, len(hs) - 1))
    d = tree.axis_points[k] - tree.axis_points[k - 1]
    return p, d / np.linalg.norm(d), float(np.interp(h, hs, tree.axis_diam)) / 2


def _ray_cylinder_depth(T_world_cam: np.ndarray, ray_cam: np.ndarray, a: np.ndarray, w: np.ndarray, r: float) -> float:
    """Optical-axis depth of the first hit of the camera ray (x, y, 1) with the infinite cylinder (a, w, r)."""
    o = T_world_cam[:3, 3] - a
    d = T_world_cam[:3, :3] @ ray_cam  # z component 1 in the camera, so the ray parameter is depth
    o_p = o - (o @ w) * w
    d_p = d - (d @ w) * w
    qa, qb, qc = d_p @ d_p, 2 * o_p @ d_p, o_p @ o_p - r * r
    disc = qb * qb - 4 * qa * qc
    assert disc > 0, "the pixel ray misses the trunk cylinder"
    return float((-qb - np.sqrt(disc)) / (2 * qa))


def test_truth_trunk_matches_scene(standard_sim):
    """The JSON trunk (line base->top, diameter) is the scene's trunk at the stated height."""
    dh = standard_sim.truth["diameter_height_m"]
    for tree, t in zip(standard_sim.scene.trees, standard_sim.truth["trees"], strict=True):
        p, w, r = _axis_at_height(tree, dh)
        base, top = np.asarray(t["trunk"]["base"]), np.asarray(t["trunk"]["top"])
        # The straight base->top line differs from the gently bowed axis (curve_m = 12 mm at mid-leader) by a few mm.
        gp, gn = np.asarray(t["local_ground"]["point"]), np.asarray(t["local_ground"]["normal"])
        u = (dh - (base - gp) @ gn) / ((top - base) @ gn)
        assert np.linalg.norm(base + u * (top - base) - p) < 0.004
        assert abs(t["trunk"]["diameter_m"] - 2 * r) < 1e-4
        assert np.dot(np.asarray(t["trunk"]["axis"]), w) > np.cos(np.radians(2.0))


def _trunk_samples(run, heights_of) -> list[dict]:
    """Bag depth at pixels on the projected true trunk, with the reference depth from the scene's trunk.

    heights_of(tree) gives the heights above local ground to sample; at each height the image row through
    the projected axis point is sampled within half a radius of the axis (the ray still meets the
    cylinder head-on), where the instance mask shows that trunk over the pixel's whole 3x3 neighbourhood.
    """
    K = run.scenario.camera
    coeff = run.truth["camera"]["depth_sigma_coeff"]
    out = []
    for side in SIDES:
        frames = run.frames(side)
        _, poses = run.world_poses(side)
        masks = {i: m for i, _, m in run.masks(side)}
        assert len(frames) == len(poses) == len(masks)
        for i, (frame, T_wc) in enumerate(zip(frames, poses, strict=True)):
            T_cw = np.linalg.inv(T_wc)
            for tree in run.scene.trees:
                for h in heights_of(tree):
                    a, w, r = _axis_at_height(tree, h)
                    pc = T_cw[:3, :3] @ a + T_cw[:3, 3]
                    if pc[2] < 0.3:
                        continue
                    u0 = K.fx * pc[0] / pc[2] + K.cx
                    v = round(K.fy * pc[1] / pc[2] + K.cy)
                    half = 0.5 * r * K.fx / pc[2]  # px
                    for u in range(int(np.ceil(u0 - half)), int(np.floor(u0 + half)) + 1):
                        if not (1 <= u < K.width - 1 and 1 <= v < K.height - 1):
                            continue
                        if np.any(masks[i][v - 1:v + 2, u - 1:u + 2] != MASK_TRUNK + tree.id):
                            continue  # occluded (weed, leaf, post) or next to the trunk's silhouette
                        ray = np.array([(u - K.cx) / K.fx, (v - K.cy) / K.fy, 1.0])
                        z_true = _ray_cylinder_depth(T_wc, ray, a, w, r)
                        # Sanity of the reference itself: about the axis depth minus the radius.
                        assert abs(z_true - (pc[2] - r)) < 0.5 * r  # oblique views shift it by a fraction of r
                        out.append({"side": side, "frame": i, "tree": tree.id, "h": h, "z": float(frame.depth[v, u]),
                                    "z_true": z_true, "sigma": coeff * z_true**2})
    return out


def _check_residuals(samples: list[dict], what: str) -> np.ndarray:
    valid = [s for s in samples if s["z"] > 0]
    # Missing depth on a clean trunk pixel is only the random dropout (1 %): allow 5 % (+2 for tiny samples).
    assert len(samples) - len(valid) <= 2 + 0.05 * len(samples), f"{what}: too much missing depth"
    res = np.array([s["z"] - s["z_true"] for s in valid])
    sig = np.array([s["sigma"] for s in valid])
    bound = 4 * sig + QUANT_M + GEOM_M
    # Gaussian noise exceeds 4 sigma with P ~ 6e-5 per pixel: none for a few samples, <= 0.1 % for thousands;
    # nothing may exceed 6 sigma (P ~ 2e-9).
    n_bad = int(np.sum(np.abs(res) > bound))
    assert n_bad <= 0.001 * len(res), f"{what}: {n_bad} of {len(res)} beyond 4 sigma"
    assert np.all(np.abs(res) < 6 * sig + QUANT_M + GEOM_M), f"{what}: residual beyond 6 sigma"
    # No bias: the median of N Gaussian residuals has sd ~1.25 sigma / sqrt(N); allow 4 of those + allowances.
    assert abs(np.median(res)) < 4 * 1.25 * np.median(sig) / np.sqrt(len(res)) + QUANT_M + GEOM_M, what
    return res / sig


def test_bag_depth_at_diameter_height_matches_truth(standard_sim):
    """Depth in the bag at the projected true trunk axis at diameter height = distance to the trunk surface."""
    dh = standard_sim.truth["diameter_height_m"]
    samples = _trunk_samples(standard_sim, lambda tree: [dh])
    assert len(samples) >= 20, f"too few unoccluded trunk pixels at diameter height ({len(samples)})"
    _check_residuals(samples, "diameter height")
    # Every tree is seen cleanly at diameter height from at least one side, and the truth says so.
    for t in standard_sim.truth["trees"]:
        sides = {s["side"] for s in samples if s["tree"] == t["id"]}
        assert sides, f"tree {t['id']} never seen cleanly at diameter height"
        for side in sides:
            assert t["observed"][side]["trunk_at_diameter_height"]


def test_bag_depth_along_clear_trunk_matches_truth(standard_sim):
    """The same along the clear trunk (every 4 cm from 0.15 m to 5 cm below the canopy): many pixels."""
    samples = _trunk_samples(standard_sim, lambda tree: np.arange(0.15, tree.clear_height - 0.05, 0.04))
    assert len(samples) >= 500
    z = _check_residuals(samples, "clear trunk")
    # The spread is the model's: sd of residual / sigma ~ 1 (the allowances add < 0.3 sigma at these ranges).
    assert 0.8 < np.std(z) < 1.3
    assert {s["tree"] for s in samples} == {t.id for t in standard_sim.scene.trees}


def test_mask_values_and_index(standard_sim):
    """Mask values: 1 + tree id (trunk), 10000 + fruit index, 60000 + post index; index.csv stamps = bag stamps."""
    run = standard_sim
    n_trees, n_fruit, n_posts = len(run.scene.trees), len(run.scene.fruit), len(run.scene.posts)
    for side in SIDES:
        stamps, _ = run.world_poses(side)
        masks = run.masks(side)
        assert [i for i, _, _ in masks] == list(range(len(stamps)))
        np.testing.assert_allclose([s for _, s, _ in masks], stamps, atol=2e-6)
        values = np.unique(np.concatenate([np.unique(m) for _, _, m in masks]))
        trunk = values[(values >= MASK_TRUNK) & (values < MASK_FRUIT)] - MASK_TRUNK
        fruit = values[(values >= MASK_FRUIT) & (values < MASK_POST)] - MASK_FRUIT
        post = values[values >= MASK_POST] - MASK_POST
        assert 0 in values
        assert set(trunk) == set(range(n_trees))  # every trunk appears in the level sweep
        assert fruit.size and fruit.max() < n_fruit
        assert post.size and post.max() < n_posts


def _fruit_pixels(run, side: str) -> tuple[np.ndarray, np.ndarray]:
    """Per mask frame and fruit: visible pixel count (F, N) and projected-disc area in pixels (F, N)."""
    fx = run.truth["camera"]["fx"]
    fruit = [f for t in run.truth["trees"] for f in t["fruit"]]
    fruit.sort(key=lambda f: f["id"])
    assert [f["id"] for f in fruit] == list(range(len(fruit)))
    pos = np.array([f["position"] for f in fruit])  # (N, 3) world
    rad = np.array([f["radius_m"] for f in fruit])
    _, poses = run.world_poses(side)
    counts, areas = [], []
    for i, _, m in run.masks(side):
        v = m[(m >= MASK_FRUIT) & (m < MASK_POST)].astype(np.int64) - MASK_FRUIT
        counts.append(np.bincount(v, minlength=len(fruit)))
        T_cw = np.linalg.inv(poses[i])
        z = pos @ T_cw[2, :3] + T_cw[2, 3]
        areas.append(np.where(z > 0.1, np.pi * (fx * rad / np.maximum(z, 1e-3)) ** 2, np.inf))
    return np.array(counts), np.array(areas)


def test_fruit_visibility_matches_masks(standard_sim):
    """visible.<side> is true exactly when some mask of that side shows >= 20 px and >= 25 % of the fruit's disc."""
    run = standard_sim
    fruit = sorted((f for t in run.truth["trees"] for f in t["fruit"]), key=lambda f: f["id"])
    seen_any = np.zeros(len(fruit), bool)
    for side in SIDES:
        counts, areas = _fruit_pixels(run, side)
        flag = np.array([f["visible"][side] for f in fruit])
        best_px = counts.max(axis=0)
        # Marked visible from a side: really visible in at least one frame of that side.
        assert np.all(best_px[flag] >= FRUIT_MIN_PIXELS)
        # The truth's rule recomputed from the masks on disk and the truth trajectory.
        ok = (counts >= FRUIT_MIN_PIXELS) & (counts / areas >= FRUIT_MIN_VISIBLE_FRACTION)
        np.testing.assert_array_equal(ok.any(axis=0), flag)
        seen_any |= best_px >= FRUIT_MIN_PIXELS
    never = np.array([not (f["visible"]["front"] or f["visible"]["back"]) for f in fruit])
    both = np.array([f["visible"]["front"] and f["visible"]["back"] for f in fruit])
    # The design asks for fruit seen from both sides, from one, and from neither.
    assert both.any() and never.any() and (~both & ~never).any()
    # Fruit invisible from both sides: never 20 px of it in any mask, unless its disc is mostly hidden.
    for side in SIDES:
        counts, areas = _fruit_pixels(run, side)
        big = (counts >= FRUIT_MIN_PIXELS) & (counts / areas >= FRUIT_MIN_VISIBLE_FRACTION)
        assert not big[:, never].any()
    # Per-tree counts agree with the per-fruit flags.
    for t in run.truth["trees"]:
        fv = t["fruit_visible"]
        assert fv["front"] == sum(f["visible"]["front"] for f in t["fruit"])
        assert fv["back"] == sum(f["visible"]["back"] for f in t["fruit"])
        assert fv["either"] == sum(f["visible"]["front"] or f["visible"]["back"] for f in t["fruit"])
        assert fv["both"] == sum(f["visible"]["front"] and f["visible"]["back"] for f in t["fruit"])
        assert t["fruit_count"] == len(t["fruit"])


def test_front_back_transform(standard_sim):
    """T_world_front @ T_front_back == T_world_back, and odom_<side> is the optical frame of its first frame."""
    truth = standard_sim.truth
    T_wf = np.asarray(truth["sides"]["front"]["T_world_odom"])
    T_wb = np.asarray(truth["sides"]["back"]["T_world_odom"])
    T_fb = np.asarray(truth["T_front_back"])
    np.testing.assert_allclose(T_wf @ T_fb, T_wb, atol=1e-7)
    np.testing.assert_allclose(T_fb[3], [0, 0, 0, 1])
    np.testing.assert_allclose(T_fb[:3, :3] @ T_fb[:3, :3].T, np.eye(3), atol=1e-7)
    # A world point (a trunk base) expressed in odom_back maps onto itself expressed in odom_front.
    p_w = np.append(truth["trees"][0]["position"], 1.0)
    p_b = np.linalg.solve(T_wb, p_w)
    p_f = np.linalg.solve(T_wf, p_w)
    np.testing.assert_allclose(T_fb @ p_b, p_f, atol=1e-6)
    # The two sides face each other across the row: optical axes roughly opposite.
    assert T_fb[:3, 2] @ np.array([0, 0, 1.0]) < -0.8
    for side, T in (("front", T_wf), ("back", T_wb)):
        _, poses = standard_sim.world_poses(side)
        np.testing.assert_allclose(poses[0], T, atol=1e-6)


def test_correlated_depth_noise_keeps_its_sd_and_comes_in_patches():
    """camera.depth_noise_correlation_px: the same per-pixel sd as white noise, but neighbouring pixels err
    together (a stereo camera's matching window), so a mean over a patch keeps most of the error."""
    from orchard_mapping.sim.render import SensorModel
    from orchard_mapping.sim.scenario import CameraSpec

    def field(corr: float, seed: int) -> np.ndarray:
        sensor = SensorModel.from_camera(CameraSpec(depth_noise_correlation_px=corr))
        return sensor.depth_noise((480, 640), np.random.default_rng(seed))

    white = field(0.0, 1)
    np.testing.assert_array_equal(white, np.random.default_rng(1).standard_normal((480, 640), dtype=np.float32))
    for seed in (1, 2):
        patchy = field(4.0, seed)
        assert 0.9 < patchy.std() < 1.1
        # neighbours 2 px apart: r = exp(-d^2 / (4 s^2)) = 0.94 for s = 4; white: ~0
        r_patchy = np.corrcoef(patchy[:, :-2].ravel(), patchy[:, 2:].ravel())[0, 1]
        r_white = np.corrcoef(white[:, :-2].ravel(), white[:, 2:].ravel())[0, 1]
        assert r_patchy > 0.85 and abs(r_white) < 0.02
        # the mean over 16 x 16 px blocks: white noise shrinks 16-fold, patchy noise far less
        blocks = lambda f: f.reshape(30, 16, 40, 16).mean(axis=(1, 3)).std()  # noqa: E731
        assert blocks(white) < 0.1 and blocks(patchy) > 0.3
