"""Local ground (core.ground): RANSAC with the trunk-axis prior vs plain RANSAC (paper: Fig. cylinderPlane)."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.ground import (
    GroundError,
    GroundParams,
    fit_local_ground,
    fit_plane_plain_ransac,
    ground_neighbourhood,
)

N_TRUE = np.array([-np.sin(np.radians(6.0)), -np.sin(np.radians(3.0)), 1.0])
N_TRUE /= np.linalg.norm(N_TRUE)  # world z up: 6 deg slope along x, 3 deg across


def _ground_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return -(N_TRUE[0] * x + N_TRUE[1] * y) / N_TRUE[2]


def scene(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (P, 3), trunk axis (3,), trunk base (3,)): sloped ground, dense weeds up to 0.4 m, a wall of
    leaves beside the tree with more points than the ground, and a leaning trunk."""
    xy = rng.uniform(-0.6, 0.6, (3000, 2))
    ground = np.c_[xy, _ground_z(*xy.T) + rng.normal(0, 0.004, len(xy))]
    clumps = rng.uniform(-0.5, 0.5, (400, 2))
    blade_h = rng.uniform(0.08, 0.4, 400)
    bxy = np.repeat(clumps, 15, axis=0)
    weeds = np.c_[bxy, _ground_z(*bxy.T) + (rng.uniform(0, 1, (400, 15)) * blade_h[:, None]).ravel()]
    leaves = np.c_[rng.uniform(-0.6, 0.6, 6000), 0.3 + rng.normal(0, 0.01, 6000), rng.uniform(0.3, 1.5, 6000)]
    axis = np.array([np.sin(np.radians(5.0)), 0.0, np.cos(np.radians(5.0))])
    base = np.array([0.0, 0.0, 0.0])
    e1 = np.cross(axis, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    t, ph = rng.uniform(0, 0.7, 2000), rng.uniform(0, 2 * np.pi, 2000)
    trunk = base + t[:, None] * axis + 0.035 * (np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2)
    return np.concatenate([ground, weeds, leaves, trunk]), axis, base


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_trunk_prior_finds_the_ground_under_weeds_and_beside_leaves(seed):
    rng = np.random.default_rng(seed)
    P, axis, base = scene(rng)
    params = GroundParams()
    idx = ground_neighbourhood(P, base + 0.05 * axis, axis, params, trunk_bottom_height=0.0)
    fit = fit_local_ground(P[idx], axis, base + 0.05 * axis, params, np.random.default_rng(seed))
    assert fit is not None
    assert np.degrees(np.arccos(min(1.0, fit.normal @ N_TRUE))) < 0.5
    assert abs(fit.point[2] - _ground_z(*fit.point[:2])) < 0.006  # height of the plane at the trunk
    assert fit.height_of(base) == pytest.approx(0.0, abs=0.006)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_plane_names_the_ground_cells_it_stands_for(seed):
    """ground_cells: the ground the plane was fitted to (scored against the terrain under them in
    benchmarks/ground.py): ground, not weed tops or leaves, spread over the disk, and the plane runs
    through them."""
    rng = np.random.default_rng(seed)
    P, axis, base = scene(rng)
    params = GroundParams()
    idx = ground_neighbourhood(P, base + 0.05 * axis, axis, params, trunk_bottom_height=0.0)
    fit = fit_local_ground(P[idx], axis, base + 0.05 * axis, params, np.random.default_rng(seed))
    assert fit is not None and fit.ground_cells is not None
    cells = fit.ground_cells
    above = cells[:, 2] - _ground_z(*cells[:, :2].T)  # (G,) m above the true ground
    assert np.all(above < 0.02) and np.all(above > -0.03)  # no weed top (8-40 cm), no leaf (30 cm up)
    assert len(cells) * 0.04**2 == pytest.approx(fit.support_m2)
    assert np.ptp(cells[:, 0]) > 0.7 and np.ptp(cells[:, 1]) > 0.7  # the disk, not a patch of it
    assert np.median(np.abs(fit.height_of(cells))) < 0.006


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_plain_ransac_takes_the_wall_of_leaves(seed):
    """The paper's Fig. cylinderPlane: without the prior, the plane with most points is not the ground."""
    rng = np.random.default_rng(seed)
    P, axis, base = scene(rng)
    fit = fit_plane_plain_ransac(P, GroundParams(), seed, axis, base)
    assert fit is not None
    assert np.degrees(np.arccos(min(1.0, abs(fit.normal @ N_TRUE)))) > 45.0


def test_too_few_points_give_no_ground_and_bad_settings_are_named():
    rng = np.random.default_rng(0)
    up = np.array([0.0, 0.0, 1.0])
    assert fit_local_ground(rng.normal(size=(10, 3)), up, np.zeros(3), GroundParams(), rng) is None
    with pytest.raises(GroundError, match="ground.max_below_fraction"):
        GroundParams(max_below_fraction=1.5)
    with pytest.raises(GroundError, match="trunk axis prior"):
        fit_local_ground(rng.normal(size=(100, 3)), np.zeros(3), np.zeros(3), GroundParams(), rng)


def test_the_ground_says_how_far_from_the_trunk_it_was_seen():
    """support_offset_m: ~0 for ground all round the trunk, ~the patch's distance for ground seen only in
    a corner of the disk (its height at the trunk is then an extrapolation the merge weighs less)."""
    rng = np.random.default_rng(0)
    axis, base = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    params = GroundParams(min_support_m2=0.05)  # the corner patch is ~0.09 m^2
    r, ph = 0.5 * np.sqrt(rng.uniform(0, 1, 4000)), rng.uniform(0, 2 * np.pi, 4000)
    xy = np.c_[r * np.cos(ph), r * np.sin(ph)]
    disk = np.c_[xy, _ground_z(*xy.T) + rng.normal(0, 0.004, len(xy))]
    corner_xy = xy[(xy[:, 0] > 0.25) & (np.abs(xy[:, 1]) < 0.2)]
    corner = np.c_[corner_xy, _ground_z(*corner_xy.T) + rng.normal(0, 0.004, len(corner_xy))]
    whole = fit_local_ground(disk, axis, base, params, np.random.default_rng(1))
    part = fit_local_ground(corner, axis, base, params, np.random.default_rng(1))
    assert whole is not None and part is not None
    assert whole.support_offset_m < 0.05
    assert 0.3 < part.support_offset_m < 0.45  # the corner's centre lies ~0.37 m out


def _undulating_ground(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(points (P, 3), normal (3,), point (3,) under the trunk) of the least-squares plane of the terrain
    seen: ground that undulates as the simulator's slope_weeds rows do (5 waves of 1.3-2.5 m, 12 cm, and
    fine roughness), seen over a little more than half of the 0.5 m disk round the trunk at (0, 0)."""
    ang = rng.uniform(0, 2 * np.pi, 13)
    wavelength = np.r_[1.8 * rng.uniform(0.7, 1.4, 5), rng.uniform(0.12, 0.35, 8)]
    k = np.stack([np.cos(ang), np.sin(ang)], 1) * (2 * np.pi / wavelength)[:, None]  # (13, 2) rad/m
    amp = np.r_[0.12 * rng.uniform(0.4, 1.0, 5) / np.sqrt(2.5), 0.015 * rng.uniform(0.5, 1.0, 8) / 2]
    phase = rng.uniform(0, 2 * np.pi, 13)

    def z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return 0.105 * x + 0.05 * y + np.sin(np.multiply.outer(x, k[:, 0]) + np.multiply.outer(y, k[:, 1]) + phase) @ amp

    r, a = 0.5 * np.sqrt(rng.uniform(0, 1, 5000)), rng.uniform(-np.pi, 0.2, 5000)
    xy = np.c_[r * np.cos(a), r * np.sin(a)]
    (gx, gy, c), *_ = np.linalg.lstsq(np.c_[xy, np.ones(len(xy))], z(*xy.T), rcond=None)
    n = np.array([-gx, -gy, 1.0])
    return np.c_[xy, z(*xy.T) + rng.normal(0, 0.004, len(xy))], n / np.linalg.norm(n), np.array([0.0, 0.0, c])


def test_undulating_ground_gives_the_plane_of_the_ground_seen():
    """The local ground is the plane of the terrain the side saw; on ground that is not a plane over the
    disk the RANSAC plane can be tangent to a part of it (7 deg off on two of these seeds) and a plane refitted within a band
    of it keeps only a strip. The ground surface grown from it (a quadratic, then cell by cell) finds the
    plane of all of it: 8 seeds, within the 1 deg goal on all but one, none beyond 3 deg."""
    up = np.array([0.0, 0.0, 1.0])
    params, plane_refit = GroundParams(), GroundParams(refine_surface="plane", refine_band_m=0.05, refine_iterations=5)
    errors, plane_errors = [], []
    for seed in range(8):
        P, n_true, p_true = _undulating_ground(np.random.default_rng(seed))
        for prm, out in ((params, errors), (plane_refit, plane_errors)):
            fit = fit_local_ground(P, up, p_true, prm, np.random.default_rng(seed))
            out.append(np.inf if fit is None else np.degrees(np.arccos(min(1.0, fit.normal @ n_true))))
    assert sum(e <= 1.0 for e in errors) >= 7 and max(errors) < 3.0, errors
    assert max(plane_errors) > 3.0, plane_errors  # the earlier refit, beside it


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_plane_goes_through_the_ground_surface_not_its_lowest_samples(seed):
    """Each 4 cm cell holds ~10 samples of the ground (noise sd 4 mm): its lowest lies ~6 mm below the
    surface. The plane through each ground cell's points near its lowest (cell_surface_band_m) is not."""
    rng = np.random.default_rng(seed)
    axis, base = np.array([0.0, 0.0, 1.0]), np.zeros(3)
    r, ph = 0.5 * np.sqrt(rng.uniform(0, 1, 5000)), rng.uniform(0, 2 * np.pi, 5000)
    xy = np.c_[r * np.cos(ph), r * np.sin(ph)]
    P = np.c_[xy, _ground_z(*xy.T) + rng.normal(0, 0.004, len(xy))]
    heights = {}
    for band in (0.0, GroundParams().cell_surface_band_m):
        fit = fit_local_ground(P, axis, base, GroundParams(cell_surface_band_m=band), np.random.default_rng(seed))
        assert fit is not None
        assert np.degrees(np.arccos(min(1.0, fit.normal @ N_TRUE))) < 0.5
        heights[band] = 1000 * (fit.point[2] - _ground_z(*fit.point[:2]))  # mm, at the trunk
    lowest, surface = heights[0.0], heights[GroundParams().cell_surface_band_m]
    assert lowest < -3.0, heights  # the lowest samples' plane sits low
    assert abs(surface) < 2.0, heights
