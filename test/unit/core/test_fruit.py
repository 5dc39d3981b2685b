"""core.fruit: fruit placed from instances and depth, one fruit per cluster of views, both sides once."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.fruit import (
    FruitError,
    FruitObservation,
    FruitParams,
    SideFruit,
    associate_sides,
    fruit_observations,
    fruit_of_side,
    fruit_offsets,
    inclusion_exclusion_count,
)
from orchard_mapping.core.types import CameraIntrinsics

INTR = CameraIntrinsics(640, 480, 615.0, 615.0, 319.5, 239.5)


def _render(centres: np.ndarray, radii: np.ndarray, T_odom_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth (H, W) m and instances (H, W) of spheres (odom) seen by a pinhole camera: ray-sphere hits."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    rays = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u, float)], -1)  # (H, W, 3)
    T_cam_odom = np.linalg.inv(T_odom_cam)
    depth = np.zeros(u.shape)
    inst = np.zeros(u.shape, np.int32)
    for k, (c, r) in enumerate(zip(centres, radii, strict=True)):
        cc = T_cam_odom[:3, :3] @ c + T_cam_odom[:3, 3]
        # |t ray - cc|^2 = r^2 with the ray's z = 1: t = depth
        a = np.sum(rays**2, -1)
        b = rays @ cc
        disc = b**2 - a * (cc @ cc - r * r)
        hit = disc > 0
        t = np.where(hit, (b - np.sqrt(np.maximum(disc, 0))) / a, np.inf)
        nearer = hit & ((depth == 0) | (t < depth))
        depth[nearer] = t[nearer]
        inst[nearer] = k + 1
    return depth.astype(np.float32), inst


def _pose(x: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = x
    return T


def test_a_whole_sphere_is_placed_within_millimetres():
    rng = np.random.default_rng(0)
    centres = np.column_stack([rng.uniform(-0.3, 0.3, 6), rng.uniform(-0.2, 0.2, 6), rng.uniform(1.0, 1.8, 6)])
    centres[:, 0] = np.linspace(-0.4, 0.4, 6)
    radii = rng.uniform(0.035, 0.045, 6)
    depth, inst = _render(centres, radii, np.eye(4))
    obs = fruit_observations(inst, depth, np.eye(4), INTR, FruitParams())
    assert len(obs) == 6
    for o in obs:
        k = o.instance - 1
        assert np.linalg.norm(o.centre - centres[k]) < 0.004
        assert abs(o.radius_m - radii[k]) < 0.002


def test_a_fruit_cut_by_the_border_or_too_small_is_not_observed():
    centres = np.array([[-0.62, 0.0, 1.2], [0.0, 0.0, 1.2]])  # the first is cut by the left border
    depth, inst = _render(centres, np.array([0.04, 0.008]), np.eye(4))  # the second is 8 mm: a bud
    assert fruit_observations(inst, depth, np.eye(4), INTR, FruitParams()) == []


def test_views_of_one_fruit_make_one_fruit_and_touching_fruit_stay_two():
    centres = np.array([[0.0, 0.0, 1.3], [0.08, 0.0, 1.3], [0.5, 0.1, 1.5]])  # first two touch (r 4 cm)
    radii = np.array([0.04, 0.04, 0.04])
    obs = []
    for k, x in enumerate(np.arange(-0.3, 0.31, 0.15)):  # five keyframes 15 cm apart
        depth, inst = _render(centres, radii, _pose(x))
        obs += fruit_observations(inst, depth, _pose(x), INTR, FruitParams(), keyframe=k)
    side = fruit_of_side("front", obs, FruitParams())
    assert len(side.positions) == 3
    d = np.linalg.norm(side.positions[:, None] - centres[None], axis=2)
    assert np.all(d.min(axis=1) < 0.005) and len(set(d.argmin(axis=1).tolist())) == 3
    assert np.all(np.abs(side.diameters_m - 0.08) < 0.004)
    # seen in fewer keyframes than min_views: dropped
    assert len(fruit_of_side("front", [o for o in obs if o.keyframe < 2], FruitParams()).positions) == 0


def _observed(rng: np.random.Generator, centres: np.ndarray, radii: np.ndarray, views: np.ndarray,
              first_id: int = 0) -> list[FruitObservation]:
    """Each fruit seen in its number of keyframes, its centre and radius a little off in each (as measured)."""
    return [FruitObservation(int(k), c + rng.normal(0, 0.002, 3), float(r * rng.uniform(0.97, 1.03)), 200, first_id + j)
            for j, (c, r, n) in enumerate(zip(centres, radii, views, strict=True)) for k in range(int(n))]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pieces_and_specks_far_smaller_than_the_sides_fruit_are_dropped(seed):
    """30 apples (r 37-43 mm, 5-10 views) and 12 pieces of fruit or red specks the pixel model took for fruit
    (r 12-25 mm, 3-4 views): the pieces go, every apple stays. A variety of small fruit (r 20 mm) keeps all."""
    rng = np.random.default_rng(seed)
    centres = np.column_stack([np.arange(42) * 0.2, rng.uniform(-0.3, 0.3, 42), rng.uniform(0.8, 2.0, 42)])
    radii = np.r_[rng.uniform(0.037, 0.043, 30), rng.uniform(0.012, 0.025, 12)]
    views = np.r_[rng.integers(5, 11, 30), rng.integers(3, 5, 12)]
    obs = _observed(rng, centres, radii, views)
    assert len(fruit_of_side("front", obs, FruitParams(min_size_of_median=0.0)).positions) == 42
    kept = fruit_of_side("front", obs, FruitParams(min_size_of_median=0.7))
    assert len(kept.positions) == 30
    assert np.all(np.linalg.norm(kept.positions[:, None] - centres[None, :30], axis=2).min(axis=1) < 0.01)
    small = _observed(rng, centres[:30], np.full(30, 0.02), views[:30])
    assert len(fruit_of_side("front", small, FruitParams(min_size_of_median=0.7)).positions) == 30


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_outline_round_two_touching_fruit_neither_joins_them_nor_sizes_them(seed):
    """30 apples (r 37-43 mm, 5-10 views), 6 of them in 3 touching pairs (centres 75 mm apart). In 3 views of
    each pair the pixel model's instance holds both (its centre between them, its radius twice a fruit's, the
    most pixels of any view), and 4 other apples have 3 views each with a red leaf beside them in their outline
    (radius x 1.6, centre 1.5 cm off). Without the rule a pair is one fruit and those 4 are sized by the large
    views; with it, 30 fruit within 4 mm of their diameters. A crop whose apples vary from 33 to 48 mm keeps
    every fruit and view."""
    rng = np.random.default_rng(seed)
    centres = np.column_stack([np.arange(30) * 0.25, rng.uniform(-0.3, 0.3, 30), rng.uniform(0.8, 2.0, 30)])
    for a in (0, 10, 20):  # fruit a and a + 1 touch
        centres[a + 1] = centres[a] + [0.075, 0.0, 0.0]
    radii = rng.uniform(0.037, 0.043, 30)
    views = rng.integers(5, 11, 30)
    obs = _observed(rng, centres, radii, views)
    for a in (0, 10, 20):
        mid = 0.5 * (centres[a] + centres[a + 1])
        obs += [FruitObservation(20 + v, mid + rng.normal(0, 0.002, 3), 0.08, 400) for v in range(3)]
    for a in (4, 8, 14, 26):
        obs += [FruitObservation(20 + v, centres[a] + [0.015, 0.0, 0.0], 1.6 * radii[a], 400) for v in range(3)]
    off = fruit_of_side("front", obs, FruitParams(max_size_of_median=0.0))
    assert len(off.positions) < 30 and np.abs(off.diameters_m - 0.08).max() > 0.03
    side = fruit_of_side("front", obs, FruitParams())
    assert len(side.positions) == 30
    nearest = np.linalg.norm(side.positions[:, None] - centres[None], axis=2).argmin(axis=1)
    assert sorted(nearest.tolist()) == list(range(30))
    assert np.abs(side.diameters_m - 2 * radii[nearest]).max() < 0.004
    varied = np.linspace(0.033, 0.048, 30)
    obs = _observed(rng, centres + [0.0, 0.0, 0.5], varied, views)
    side = fruit_of_side("front", obs, FruitParams())
    assert len(side.positions) == 30 and sorted(side.views.tolist()) == sorted(views.tolist())  # every view kept


def test_both_sides_count_each_fruit_once_and_the_baselines_differ():
    rng = np.random.default_rng(5)
    true = np.column_stack([np.arange(20) * 0.09, rng.uniform(-0.3, 0.3, 20), rng.uniform(0.8, 2.0, 20)])
    dia = np.full(20, 0.08)
    f_idx, b_idx = np.arange(0, 14), np.arange(8, 20)  # 6 seen from both sides
    front = SideFruit("front", true[f_idx] + rng.normal(0, 0.005, (14, 3)), dia[f_idx], np.full(14, 4))
    back = SideFruit("back", true[b_idx] + rng.normal(0, 0.005, (12, 3)), dia[b_idx], np.full(12, 4))
    row = associate_sides(front, back, FruitParams())
    assert len(row.positions) == 20
    assert (row.seen_from == "both").sum() == 6
    both = row.seen_from == "both"
    assert np.all(f_idx[row.front_index[both]] == b_idx[row.back_index[both]])
    assert inclusion_exclusion_count(front, back, FruitParams()) == 20
    # fruit one touching distance apart on the other side are not merged: 0.09 m apart, gate 1 x radius (4 cm)
    # (the shift onto the front side turned off: it would find the 4.5 cm the whole side moved)
    shifted = SideFruit("back", back.positions + [0.09 / 2, 0, 0], back.diameters_m, back.views)
    assert (associate_sides(front, shifted, FruitParams(align_gate_m=0.0)).seen_from == "both").sum() == 0


def _crown(rng: np.random.Generator, n: int, x0: float) -> np.ndarray:
    """(n, 3) fruit centres hanging in a 1 m crown at x0, none closer than 9 cm."""
    out: list[np.ndarray] = []
    while len(out) < n:
        c = np.array([x0 + rng.uniform(-0.5, 0.5), rng.uniform(-0.35, 0.35), rng.uniform(1.0, 2.0)])
        if all(np.linalg.norm(c - o) > 0.09 for o in out):
            out.append(c)
    return np.array(out)


@pytest.mark.parametrize("seed", range(3))
def test_a_side_left_centimetres_off_by_the_merge_is_shifted_back_before_matching(seed):
    """Three crowns; the back side's fruit moved by a merge error (2-4 deg about a near-vertical axis through
    the row's middle and 6-10 cm: twice the gate and more), with 5 mm noise; 12 of each crown's 20 fruit seen
    from both sides. Without the shift hardly a fruit is matched and the row is counted 1.5 times; with it
    most shared fruit (29-36 of 36 on these seeds; a fruit whose neighbourhood turned more than the kernel is
    still missed) are matched, each to itself. Two sides that share no fruit get no shift."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    fronts, backs, shared = [], [], 0
    axis = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.2, 3)
    R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(rng.uniform(2, 4))).as_matrix()
    move = rng.normal(size=3)
    move *= rng.uniform(0.06, 0.10) / np.linalg.norm(move)
    mid = np.array([1.2, 0.0, 1.5])
    for k in range(3):
        true = _crown(rng, 20, 1.2 * k)
        f = rng.permutation(20)[:16]
        b = np.concatenate([f[:12], np.setdiff1d(np.arange(20), f)])  # 12 shared, 4 back only
        shared += 12
        fronts.append(true[f] + rng.normal(0, 0.005, (len(f), 3)))
        backs.append((true[b] - mid) @ R.T + mid + move + rng.normal(0, 0.005, (len(b), 3)))
    front = SideFruit("front", np.vstack(fronts), np.full(48, 0.08), np.full(48, 5))
    back = SideFruit("back", np.vstack(backs), np.full(48, 0.08), np.full(48, 5))
    off = associate_sides(front, back, FruitParams(align_gate_m=0.0))
    assert (off.seen_from == "both").sum() <= 6 and len(off.positions) >= 90
    row = associate_sides(front, back, FruitParams())
    both = row.seen_from == "both"
    assert both.sum() >= 0.75 * shared and len(row.positions) <= 60 + 0.25 * shared
    pairs = set(zip(row.front_index[both].tolist(), row.back_index[both].tolist(), strict=True))
    right = {(i, i) for i in range(48) if i % 16 < 12}  # a crown's 12 shared fruit come first on both sides
    assert len(pairs & right) >= 0.75 * shared and len(pairs - right) <= 2
    # unrelated sides: other crowns (no shared fruit) get no shift, and no fruit of theirs is matched
    other = SideFruit("back", np.vstack([_crown(rng, 20, 1.2 * k) for k in range(3)]), np.full(60, 0.08),
                      np.full(60, 5))
    assert np.abs(fruit_offsets(front, other, FruitParams())).max() == 0.0


def test_bad_input_is_refused_with_what_is_wrong():
    with pytest.raises(FruitError, match="depth must be"):
        fruit_observations(np.zeros((4, 4), int), np.zeros((5, 4)), np.eye(4), INTR, FruitParams())
    with pytest.raises(FruitError, match="T_odom_cam"):
        fruit_observations(np.zeros((4, 4), int), np.zeros((4, 4)), np.eye(3), INTR, FruitParams())
    with pytest.raises(FruitError, match="max_radius_m"):
        FruitParams(min_radius_m=0.1, max_radius_m=0.05)
