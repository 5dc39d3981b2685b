"""Trunk cylinders from silhouettes alone (core.silhouette): outlines of masks in calibrated views, no depth."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.cylinder import Cylinder, CylinderError
from orchard_mapping.core.silhouette import cylinder_from_silhouettes, outline_planes
from orchard_mapping.core.types import CameraIntrinsics

INTR = CameraIntrinsics(640, 480, 615.0, 615.0, 319.5, 239.5)


def _camera(x: float, y: float = -1.25, z: float = 0.6, yaw_deg: float = 0.0) -> np.ndarray:
    """(4, 4) T_map_cam of a level camera at (x, y, z) m looking +y (map z up), turned yaw_deg about z."""
    yaw = np.radians(yaw_deg)
    fwd = np.array([np.sin(yaw), np.cos(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([np.cross(down, fwd), down, fwd], 1)  # x right, y down, z forward
    T[:3, 3] = [x, y, z]
    return T


def _mask(cyl: Cylinder, T_map_cam: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels whose ray through the pixel centre meets the (infinite) cylinder."""
    v, u = np.mgrid[0:INTR.height, 0:INTR.width]
    d = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones(u.shape)], -1).reshape(-1, 3)
    c = cyl.transformed(np.linalg.inv(T_map_cam))
    # distance between the ray line (through the camera centre) and the axis line
    cr = np.cross(d, c.axis)
    dist = np.abs(cr @ c.origin) / np.linalg.norm(cr, axis=1)
    return (dist < c.radius).reshape(INTR.height, INTR.width)


def _planes(cyl: Cylinder, xs: list[float], rows=(200, 300), notch_view: int | None = None):
    planes = []
    for i, x in enumerate(xs):
        T = _camera(x, yaw_deg=np.degrees(np.arctan2(cyl.origin[0] - x, 1.25)) * 0.5)
        m = _mask(cyl, T)
        if i == notch_view:
            # a leaf in front of the trunk's right edge on some rows: the outline is notched there
            cols = np.flatnonzero(m[250])
            m[240:262, cols[-1] - 6:cols[-1] + 1] = False
        planes += outline_planes(m, T, INTR, rows, i)
    return planes


def test_two_or_more_views_give_the_trunk_cylinder_without_depth():
    lean = np.radians(3.0)
    truth = Cylinder(np.array([np.sin(lean), 0.0, np.cos(lean)]), np.array([0.1, 0.0, 0.6]), 0.035)
    planes = _planes(truth, [-0.5, -0.2, 0.1, 0.4, 0.7])
    assert len(planes) == 10
    cyl, res = cylinder_from_silhouettes(planes, origin_hint=truth.origin)
    assert abs(cyl.radius - truth.radius) < 0.0005  # m: the outlines' sub-pixel line fits
    assert np.degrees(np.arccos(abs(cyl.axis @ truth.axis))) < 1.0
    d = cyl.origin - truth.origin
    assert np.linalg.norm(d - (d @ truth.axis) * truth.axis) < 0.002  # m, across the axis
    assert np.abs(res).max() < 0.001


def test_a_notched_outline_is_left_out_of_the_line():
    truth = Cylinder(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.6]), 0.04)
    clean, _ = cylinder_from_silhouettes(_planes(truth, [-0.6, -0.3, 0.0, 0.3, 0.6]), origin_hint=truth.origin)
    notched, _ = cylinder_from_silhouettes(_planes(truth, [-0.6, -0.3, 0.0, 0.3, 0.6], notch_view=2),
                                           origin_hint=truth.origin)
    assert abs(notched.radius - truth.radius) < 0.0007
    assert abs(notched.radius - clean.radius) < 0.0005
    # without the robust line the notch would pull the right outline 3 px in over a fifth of the rows
    m = _mask(truth, _camera(0.0))
    cols = np.flatnonzero(m[250])
    m[240:262, cols[-1] - 6:cols[-1] + 1] = False
    right = [p for p in outline_planes(m, _camera(0.0), INTR, (200, 300), 0) if p.side == 1]
    exact = [p for p in outline_planes(_mask(truth, _camera(0.0)), _camera(0.0), INTR, (200, 300), 0) if p.side == 1]
    assert len(right) == 1 and np.degrees(np.arccos(np.clip(right[0].normal @ exact[0].normal, -1, 1))) < 0.05


def test_one_view_is_refused_with_a_reason():
    truth = Cylinder(np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 0.6]), 0.04)
    with pytest.raises(CylinderError, match="two"):
        cylinder_from_silhouettes(_planes(truth, [0.0]))
    # a trunk cut by the image border has no outline on that side
    T = _camera(0.0, yaw_deg=27.4)  # the trunk straddles the left image border
    m = _mask(truth, T)
    assert m[:, 0].any() or m[:, -1].any()
    assert len(outline_planes(m, T, INTR, (200, 300), 0)) <= 1
