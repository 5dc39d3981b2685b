"""Trunk cylinder fitting (core.cylinder): the minimal solver, RANSAC + LM, the 2D terms of eq. objectCylinder."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.cylinder import (
    Cylinder,
    CylinderView,
    cylinder_from_oriented_points,
    fit_cylinder,
    point_distance,
)
from orchard_mapping.core.types import CameraIntrinsics

INTR = CameraIntrinsics(640, 480, 615.0, 615.0, 319.5, 239.5)
UP = np.array([0.0, -1.0, 0.0])  # optical frame: y down


def _true_cylinder(lean_deg: float = 5.0, radius: float = 0.035) -> Cylinder:
    lean = np.radians(lean_deg)
    return Cylinder(np.array([np.sin(lean), -np.cos(lean), 0.0]), np.array([0.0, 0.0, 1.25]), radius)


def render(cyl: Cylinder, T_odom_cam: np.ndarray, rng: np.random.Generator, noise: float = 0.004,
           occluder_cols: tuple[int, int] | None = None, half_height: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """(depth (H, W) float32 m with noise coeff * z^2, trunk mask (H, W) bool) of a cylinder before a wall at 4 m.

    occluder_cols: a leaf at 0.8 m covering these image columns on the upper half of the image.
    """
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    d = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1).reshape(-1, 3)
    c = cyl.transformed(np.linalg.inv(T_odom_cam))
    da, oa = np.cross(d, c.axis), np.cross(-c.origin, c.axis)
    A, B, C = np.einsum("ij,ij->i", da, da), 2 * da @ oa, oa @ oa - c.radius**2
    disc = B * B - 4 * A * C
    s = np.where(disc > 0, (-B - np.sqrt(np.maximum(disc, 0))) / (2 * A), np.inf)
    h = (np.where(np.isfinite(s), s, 0.0)[:, None] * d - c.origin) @ c.axis
    hit = (disc > 0) & (np.abs(h) < half_height)
    z = np.where(hit, s, 4.0).reshape(INTR.height, INTR.width)
    mask = hit.reshape(INTR.height, INTR.width)
    if occluder_cols is not None:
        occ = np.zeros_like(mask)
        occ[: INTR.height // 2, occluder_cols[0]:occluder_cols[1]] = True
        z = np.where(occ, 0.8, z)
        mask &= ~occ
    z = z + rng.standard_normal(z.shape) * noise * z**2
    return z.astype(np.float32), mask


def surface_points(cyl: Cylinder, rng: np.random.Generator, n: int = 6000, noise: float = 0.002,
                   radial_bias: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Fused-cloud stand-in: (N, 3) points of the camera-facing half (z < axis), (N, 3) true normals."""
    h = rng.uniform(-0.3, 0.3, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    e1 = np.cross(cyl.axis, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(cyl.axis, e1)
    radial = np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2
    P = cyl.origin + h[:, None] * cyl.axis + (cyl.radius + radial_bias) * radial
    keep = P[:, 2] < cyl.origin[2]
    return P[keep] + rng.normal(0, noise, (keep.sum(), 3)), radial[keep]


def _views(cyl: Cylinder, rng: np.random.Generator, **kw) -> list[CylinderView]:
    views = []
    for x in np.linspace(-0.3, 0.3, 5):
        T = np.eye(4)
        T[0, 3] = x
        depth, mask = render(cyl, T, rng, **kw)
        views.append(CylinderView(T, mask, depth))
    return views


def test_two_oriented_points_give_the_cylinder():
    cyl = _true_cylinder()
    P, N = surface_points(cyl, np.random.default_rng(0), n=200, noise=0.0)
    got = cylinder_from_oriented_points(P[[0, 7]], N[[0, 7]], UP)
    assert got is not None
    assert got.radius == pytest.approx(cyl.radius, abs=1e-9)
    assert got.axis @ cyl.axis == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(point_distance(P, got), 0.0, atol=1e-9)
    assert cylinder_from_oriented_points(P[[0, 0]], N[[0, 0]], UP) is None  # parallel normals: no axis


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("use_2d", [False, True])
def test_fit_recovers_the_trunk(seed, use_2d):
    rng = np.random.default_rng(seed)
    cyl = _true_cylinder()
    P, N = surface_points(cyl, rng)
    fit = fit_cylinder(P, N, _views(cyl, rng), INTR, np.random.default_rng(seed), up=UP, use_2d=use_2d)
    assert abs(fit.cylinder.radius - cyl.radius) < 0.0005
    assert np.degrees(np.arccos(min(1.0, fit.cylinder.axis @ cyl.axis))) < 0.5
    assert fit.used_2d == use_2d
    assert (fit.n_2d > 1000) == use_2d


@pytest.mark.parametrize("seed", [0, 1])
def test_the_2d_term_pulls_an_inflated_surface_back_to_the_silhouette(seed):
    """3D points 2.5 mm outside the true surface (as mixed pixels at a fused trunk's edges do): the 3D-only
    fit reports the trunk too large, as the paper found; the mask edges and depth pixels correct it."""
    rng = np.random.default_rng(seed)
    cyl = _true_cylinder()
    P, N = surface_points(cyl, rng, radial_bias=0.0025)
    views = _views(cyl, rng)
    only_3d = fit_cylinder(P, N, views, INTR, np.random.default_rng(seed), up=UP, use_2d=False)
    with_2d = fit_cylinder(P, N, views, INTR, np.random.default_rng(seed), up=UP, use_2d=True)
    assert only_3d.cylinder.radius - cyl.radius > 0.002
    assert abs(with_2d.cylinder.radius - cyl.radius) < 0.0008


def test_an_occluded_edge_is_not_taken_for_the_trunk_silhouette():
    """A leaf in front of the trunk's left edge on the upper rows: those rows' left edges are occlusion
    boundaries and must not shrink the radius."""
    rng = np.random.default_rng(5)
    cyl = _true_cylinder(lean_deg=0.0)
    P, N = surface_points(cyl, rng)
    views = []
    for x in np.linspace(-0.2, 0.2, 4):
        T = np.eye(4)
        T[0, 3] = x
        u_axis = int(round(INTR.fx * (cyl.origin[0] - x) / cyl.origin[2] + INTR.cx))
        depth, mask = render(cyl, T, rng, occluder_cols=(u_axis - 40, u_axis - 5))
        views.append(CylinderView(T, mask, depth))
    fit = fit_cylinder(P, N, views, INTR, np.random.default_rng(0), up=UP, use_2d=True)
    assert abs(fit.cylinder.radius - cyl.radius) < 0.0008


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("grow_px", [-3, 3])
def test_mask_edges_that_stray_from_the_trunk_are_moved_to_its_depth_edge(seed, grow_px):
    """A learned mask 3 px short of (or past) the trunk's edges on every row pulls the 2D fit's radius
    in (out) by several millimetres; moving each edge to the depth discontinuity within reach restores it."""
    import cv2

    rng = np.random.default_rng(seed)
    cyl = _true_cylinder()
    P, N = surface_points(cyl, rng)
    kernel = np.ones((1, 2 * abs(grow_px) + 1), np.uint8)  # horizontal: rows keep their extent
    views = []
    for v in _views(cyl, rng):
        m = v.mask.astype(np.uint8)
        m = cv2.dilate(m, kernel) if grow_px > 0 else cv2.erode(m, kernel)
        views.append(CylinderView(v.T_odom_cam, m.astype(bool), v.depth))
    raw = fit_cylinder(P, N, views, INTR, np.random.default_rng(seed), up=UP, use_2d=True)
    snapped = fit_cylinder(P, N, views, INTR, np.random.default_rng(seed), up=UP, use_2d=True, edge_snap_px=6)
    assert np.sign(raw.cylinder.radius - cyl.radius) == np.sign(grow_px)
    assert abs(raw.cylinder.radius - cyl.radius) > 0.0015
    assert abs(snapped.cylinder.radius - cyl.radius) < 0.0008


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_tapered_trunk_seen_from_one_side_keeps_its_axis(seed):
    """The visible half of a trunk 70 mm thick at the bottom and 58 mm at 0.7 m (the simulator's taper):
    a cylinder fit tilts away from the camera by about the taper's half-angle (0.5 deg), which the two sides
    of a row would double into a merge error; the cone fit keeps the axis."""
    from orchard_mapping.core.cylinder import refine_cone_axis

    rng = np.random.default_rng(seed)
    axis = np.array([0.0, -1.0, 0.0])  # optical frame: up is -y; the camera looks along +z at the trunk
    h = rng.uniform(0.0, 0.7, 8000)
    ph = rng.uniform(-np.pi / 2, np.pi / 2, 8000)  # the half facing the camera (-z side)
    r = 0.035 - (0.006 / 0.7) * h
    origin = np.array([0.0, 0.5, 1.5])
    P = origin + h[:, None] * axis + r[:, None] * np.stack([np.sin(ph), np.zeros_like(ph), -np.cos(ph)], 1)
    P += rng.normal(0, 0.001, P.shape)
    N = np.stack([np.sin(ph), np.zeros_like(ph), -np.cos(ph)], 1)
    cyl = fit_cylinder(P, N, [], INTR, np.random.default_rng(seed), up=UP, use_2d=False)
    tilt = np.degrees(np.arccos(min(1.0, abs(cyl.cylinder.axis @ axis))))
    cone, k = refine_cone_axis(P, cyl.cylinder, threshold_m=0.016)
    assert tilt > 0.3
    assert np.degrees(np.arccos(min(1.0, abs(cone.axis @ axis)))) < 0.1
    assert k == pytest.approx(-0.006 / 0.7, abs=0.002)


def _capture_least_squares(monkeypatch) -> list:
    """The (fun, jac, number of parameters) of every least_squares call core.cylinder makes."""
    import orchard_mapping.core.cylinder as cylinder_module

    calls: list = []
    real = cylinder_module.least_squares

    def spy(fun, x0, jac="2-point", **kw):
        calls.append((fun, jac, len(x0)))
        return real(fun, x0, jac=jac, **kw)

    monkeypatch.setattr(cylinder_module, "least_squares", spy)
    return calls


def _central_differences(fun, x: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    return np.stack([(fun(x + eps * e) - fun(x - eps * e)) / (2 * eps) for e in np.eye(len(x))], axis=1)


def test_the_closed_form_jacobians_are_the_residuals_derivatives(monkeypatch):
    """The fits' Jacobians are written out by hand (their speed): the cone's, the 3D term's, eq.
    objectCylinder's 2D terms and the two-side fit's shared radius. Away from the optimum they must agree
    with central differences of the residuals they go with."""
    from orchard_mapping.core.cylinder import fit_cylinders_shared_radius, refine_cone_axis

    rng = np.random.default_rng(3)
    cyl = _true_cylinder(lean_deg=7.0)
    P, N = surface_points(cyl, rng)
    views = _views(cyl, rng)
    calls = _capture_least_squares(monkeypatch)
    refine_cone_axis(P, cyl, threshold_m=0.02)
    fit_cylinder(P, N, [], INTR, rng, up=UP, use_2d=False)
    fit_cylinder(P, N, views, INTR, rng, up=UP, use_2d=True, edge_snap_px=3)
    fit_cylinders_shared_radius([(P, N, views[:3], cyl), (P, N, views[3:], cyl)], INTR, rng)
    assert [n for _, _, n in calls] == [6, 5, 5, 9] and all(callable(jac) for _, jac, _ in calls)
    for fun, jac, n in calls:
        x = rng.normal(0, 0.02, n)
        expected = _central_differences(fun, x)
        assert np.max(np.abs(jac(x) - expected)) < 1e-4 * np.max(np.abs(expected))


def test_grouped_medians_are_numpys():
    from orchard_mapping.core.geometry import group_medians

    rng = np.random.default_rng(0)
    groups, values = rng.integers(0, 40, 999), rng.normal(size=999)
    keys, med = group_medians(groups, values)
    assert list(keys) == sorted(set(groups.tolist()))
    assert np.allclose(med, [np.median(values[groups == k]) for k in keys], rtol=0, atol=1e-15)
