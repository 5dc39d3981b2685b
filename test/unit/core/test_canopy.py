"""core.canopy: alpha-complex volume against analytic solids, robust tree height."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.canopy import (
    CanopyError,
    alpha_complex,
    alpha_complex_volume,
    alpha_regions,
    mirrored_share,
    tree_height,
)


def _sphere_surface(rng: np.random.Generator, n: int, r: float) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    return r * d / np.linalg.norm(d, axis=1, keepdims=True)


def _box_samples(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, n_surf: int, n_in: int) -> np.ndarray:
    """Points on the faces (area-weighted) and inside an axis-aligned box. The face points carry 10 um of noise,
    as any sensor's: thousands of exactly coplanar points are qhull's degenerate case (the L's Delaunay took
    15 s, 1.2 s with the noise; the volumes move by < 0.1 %)."""
    size = hi - lo
    areas = np.array([size[1] * size[2], size[0] * size[2], size[0] * size[1]] * 2)
    face = rng.choice(6, n_surf, p=areas / areas.sum())
    p = lo + rng.uniform(0, 1, (n_surf, 3)) * size
    ax = face % 3
    p[np.arange(n_surf), ax] = np.where(face < 3, lo[ax], hi[ax]) + rng.normal(0, 1e-5, n_surf)
    return np.vstack([p, lo + rng.uniform(0, 1, (n_in, 3)) * size])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sphere_surface_points_give_the_ball_volume(seed):
    """Surface points only (as a camera sees a canopy) with alpha above the radius: the inscribed polyhedron
    of 4000 points misses ~1/n^(2/3) of the ball, ~0.5 %: within 2 %."""
    rng = np.random.default_rng(seed)
    r = 0.5
    vol = alpha_complex_volume(_sphere_surface(rng, 4000, r) + [2.0, -1.0, 1.0], alpha_m=0.8)
    assert vol == pytest.approx(4 / 3 * np.pi * r**3, rel=0.02)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_box_volume(seed):
    """A 0.8 x 0.6 x 1.0 m box, faces at ~2 cm spacing plus interior points: within 1 % at alpha 0.8 and 0.2."""
    rng = np.random.default_rng(seed)
    pts = _box_samples(rng, np.zeros(3), np.array([0.8, 0.6, 1.0]), 8000, 2000)
    for alpha in (0.8, 0.2):
        assert alpha_complex_volume(pts, alpha_m=alpha) == pytest.approx(0.48, rel=0.01)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_l_shape_hull_at_large_alpha_true_volume_at_small(seed):
    """An L of two boxes (1 x 0.4 x 0.4 and 0.4 x 0.4 x 1, true volume 0.256 m^3, hull 0.328 m^3 across
    its notch): at alpha 10 m the complex is the convex hull; at alpha 0.2 m (10x the ~2 cm face sampling, under half the 0.6 m notch) the notch
    stays empty: within 5 % above it."""
    rng = np.random.default_rng(seed)
    a = _box_samples(rng, np.zeros(3), np.array([1.0, 0.4, 0.4]), 6000, 0)
    b = _box_samples(rng, np.zeros(3), np.array([0.4, 0.4, 1.0]), 6000, 0)
    # face points strictly inside the other box are not on the L's surface; interior points fill the L
    a = a[~np.all((a > 1e-9) & (a < [0.4, 0.4, 1.0]), axis=1)]
    b = b[~np.all((b > 1e-9) & (b < [1.0, 0.4, 0.4]), axis=1)]
    inner = rng.uniform(0, 1, (12000, 3)) * [1.0, 0.4, 1.0]
    inner = inner[(inner[:, 0] <= 0.4) | (inner[:, 2] <= 0.4)]
    pts = np.vstack([a, b, inner])
    true = 1.0 * 0.4 * 0.4 + 0.4 * 0.4 * 0.6  # 0.256
    hull = true + 0.5 * 0.6 * 0.6 * 0.4
    assert alpha_complex_volume(pts, alpha_m=10.0) == pytest.approx(hull, rel=0.02)
    # the complex rounds the L's re-entrant edge (~alpha^2 (1 - pi/4) x 0.4 m, plus sampling): seeds 0-2
    # gave +3 %; the hull is +28 %
    assert true <= alpha_complex_volume(pts, alpha_m=0.2) <= 1.05 * true


def test_alpha_regions_counts_separate_solids():
    rng = np.random.default_rng(3)
    pts = np.vstack([_box_samples(rng, np.zeros(3), np.full(3, 0.3), 2000, 500),
                     _box_samples(rng, np.array([0.6, 0, 0]), np.array([0.9, 0.3, 0.3]), 2000, 500)])
    n, _ = alpha_regions(alpha_complex(pts, 0.1))
    assert n == 2
    n_big, _ = alpha_regions(alpha_complex(pts, 5.0))
    assert n_big == 1


def test_bad_input_is_a_typed_error():
    with pytest.raises(CanopyError):
        alpha_complex_volume(np.zeros((5, 2)), 0.8)
    with pytest.raises(CanopyError):
        alpha_complex_volume(np.zeros((5, 3)), 0.0)
    assert alpha_complex_volume(np.zeros((3, 3)), 0.8) == 0.0


def _tree(rng: np.random.Generator, normal: np.ndarray, n_flying: int) -> tuple[np.ndarray, float]:
    """Trunk cylinder (r 4 cm, 0-0.7 m) and an ellipsoid canopy surface (0.5, 0.4, 0.6 m about 1.3 m) on
    a plane through the origin with the given up normal; flying points 0.3-1 m above. (points, true height)."""
    n = normal / np.linalg.norm(normal)
    a = rng.uniform(0, 2 * np.pi, 3000)
    trunk = np.c_[0.04 * np.cos(a), 0.04 * np.sin(a), rng.uniform(0, 0.7, 3000)]
    crown = _sphere_surface(rng, 20000, 1.0) * [0.5, 0.4, 0.6] + [0, 0, 1.3]
    pts = np.vstack([trunk, crown]) + rng.normal(0, 0.002, (23000, 3))
    true = float(np.max(pts @ n))
    top = pts[np.argmax(pts @ n)]
    fly = top + np.c_[rng.normal(0, 0.2, (n_flying, 2)), rng.uniform(0.3, 1.0, n_flying)]
    return np.vstack([pts, fly]), true


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.1, -0.05, 1.0)])
def test_tree_height_ignores_flying_points(seed, normal):
    """The raw maximum takes the flying points (0.3-1 m off); the supported top is within 2 cm."""
    rng = np.random.default_rng(seed)
    n = np.array(normal)
    pts, true = _tree(rng, n, 10)
    h = tree_height(pts, np.zeros(3), n, support_radius_m=0.03, min_support=3)
    assert abs(h - true) < 0.02
    assert tree_height(pts, np.zeros(3), n, support_radius_m=0.03, min_support=0) > true + 0.25


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_canopy_begins_where_the_branches_do_not_at_the_top_of_the_leader(seed):
    """A trunk (radius 3 cm) rising through the crown to 2.2 m, the crown an ellipsoid shell from 0.7 to
    2.1 m, grass up to 0.15 m round the foot and a stray leaf cluster at 0.4 m touching nothing: the
    canopy's base is found within 4 cm of 0.7 m."""
    from orchard_mapping.core.canopy import canopy_base_height

    rng = np.random.default_rng(seed)
    z = rng.uniform(0, 2.2, 4000)
    a = rng.uniform(0, 2 * np.pi, 4000)
    trunk = np.column_stack([0.03 * np.cos(a), 0.03 * np.sin(a), z])
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    crown = u * [0.5, 0.45, 0.7] + [0, 0, 1.4]
    grass = np.column_stack([rng.uniform(-0.6, 0.6, (3000, 2)), rng.uniform(0, 0.15, 3000)])
    stray = rng.normal([0.3, 0.0, 0.4], 0.01, (30, 3))
    pts = np.concatenate([trunk, crown, grass, stray])
    base = canopy_base_height(pts, np.zeros(3), np.array([0, 0, 1.0]), trunk_radius_m=0.03, body_cell_m=0.05)
    assert abs(base - 0.7) < 0.04, base


def test_the_main_body_leaves_a_wire_stub_above_the_crown_out():
    from orchard_mapping.core.canopy import main_body, tree_height

    rng = np.random.default_rng(0)
    u = rng.normal(size=(20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    crown = u * [0.5, 0.45, 0.6] + [0, 0, 1.4]  # top at 2.0 m
    stub = np.column_stack([np.arange(-0.4, -0.15, 0.005), np.zeros(50), np.full(50, 2.16)])  # 16 cm above it
    pts = np.concatenate([crown, stub])
    body = main_body(pts, 0.05)
    assert body[:len(crown)].all() and not body[len(crown):].any()
    h = tree_height(pts[body], np.zeros(3), np.array([0, 0, 1.0]), support_radius_m=0.03, min_support=3)
    assert abs(h - 2.0) < 0.01


def _leafy_ball(rng: np.random.Generator, centre: tuple[float, float, float], r: float, n: int) -> np.ndarray:
    """(n, 3) points filling a ball (a crown's leaves, seen through its gaps)."""
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.asarray(centre) + d * (r * rng.uniform(size=(n, 1)) ** (1 / 3))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_interlocking_crowns_get_back_the_volume_a_split_gives_the_neighbour(seed):
    """Two leafy balls (r 0.5 m) 0.7 m apart, split at the mid-plane as the cutting planes split a row: each
    loses the cap beyond the cut (6 % of its volume). The neighbour's points in the mirror image of its far half
    give it back; two balls 1.2 m apart share nothing."""
    rng = np.random.default_rng(seed)
    r, along = 0.5, np.array([1.0, 0.0, 0.0])
    true_ball = 4 / 3 * np.pi * r**3
    a, b = _leafy_ball(rng, (0.0, 0, 1.5), r, 20000), _leafy_ball(rng, (0.7, 0, 1.5), r, 20000)
    pts = np.concatenate([a, b])
    own, other = pts[pts[:, 0] < 0.35], pts[pts[:, 0] >= 0.35]
    split = alpha_complex_volume(own, 0.8)
    share = mirrored_share(own, other, np.array([0.0, 0.0, 0.0]), along, 0.05)
    shared = alpha_complex_volume(np.concatenate([own, other[share]]), 0.8)
    assert split < 0.955 * true_ball, split / true_ball
    assert abs(shared / true_ball - 1) < 0.03, shared / true_ball
    assert 0 < share.sum() < 0.5 * len(b)  # the lens, not the neighbour's whole crown
    far = _leafy_ball(rng, (1.2, 0, 1.5), r, 20000)
    assert not mirrored_share(a, far, np.zeros(3), along, 0.05).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_wire_over_the_crown_is_not_its_top_but_an_upright_leader_is(seed):
    """A crown (ellipsoid shell, top 2.0 m) with a trellis wire 5 cm above it (two copies 2.5 cm apart, as the
    two sides' merge leaves a wire, 1.5 m along the row): the height is the crown's. An upright leader 25 cm
    above the crown, as thin as the wire: the height is the leader's tip."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    crown = np.array([0.0, 0.0, 1.4]) + d * [0.5, 0.4, 0.6] + rng.normal(0, 0.003, (20000, 3))
    x = rng.uniform(-0.75, 0.75, 300)
    wire = np.concatenate([np.c_[x[:150], np.full(150, 0.0), np.full(150, 2.05)],
                           np.c_[x[150:], np.full(150, 0.025), np.full(150, 2.05)]]) + rng.normal(0, 0.003, (300, 3))
    up, foot = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    kw = dict(support_radius_m=0.03, min_support=3)
    top = float(crown[:, 2].max())
    assert abs(tree_height(np.vstack([crown, wire]), foot, up, **kw) - top) < 0.01
    z = np.linspace(2.0, 2.25, 60)
    leader = np.c_[rng.normal(0, 0.005, (60, 2)), z]
    assert abs(tree_height(np.vstack([crown, leader]), foot, up, **kw) - 2.25) < 0.01
