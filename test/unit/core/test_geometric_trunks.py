"""The geometric trunk finder on synthetic side clouds: round vertical columns found, posts told apart,
weeds and leaves left out; and the depth mask a column makes in a keyframe."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.detection import CLASS_TRUNK
from orchard_mapping.core.geometric_trunks import (
    TrunkCandidate,
    column_detections,
    columns_to_model,
    cylinder_mask,
    find_trunk_candidates,
    on_tree_column,
)
from orchard_mapping.core.geometry import make_transform
from orchard_mapping.core.types import CameraIntrinsics

INTR = CameraIntrinsics(width=640, height=480, fx=615.0, fy=615.0, cx=320.0, cy=240.0)


def _ground_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.03 * y + 0.03 * np.sin(1.1 * x)


def _shell(rng, centre, radius, z0, z1, n, taper=0.0, facing=True):
    """Points on a (tapered) vertical cylinder's surface between heights z0, z1 above centre's z, the half
    facing the cameras (y < centre y) plus a little of the far half, as a fused cloud sees it."""
    z = rng.uniform(z0, z1, n)
    lo, hi = (np.pi * 0.9, np.pi * 2.1) if facing else (0, 2 * np.pi)
    ph = rng.uniform(lo, hi, n)
    r = radius + taper * z + rng.normal(0, 0.002, n)
    return np.stack([centre[0] + r * np.cos(ph), centre[1] + r * np.sin(ph), centre[2] + z], 1)


def _blob(rng, centre, size, n):
    return centre + rng.normal(0, 1, (n, 3)) * size


def _side_cloud(seed: int):
    """A side: 4 trees (trunks 3-4.5 cm radius, tapering, canopies from 0.65 m), a post (5 cm, to 2.5 m), weeds
    and hanging leaves; cameras at y = -1.3 m, 1 m up, looking across the row (+y)."""
    rng = np.random.default_rng(seed)
    gx, gy = np.meshgrid(np.arange(-1.0, 5.5, 0.012), np.arange(-1.8, 0.6, 0.012))
    gx, gy = gx.ravel(), gy.ravel()
    pts = [np.stack([gx, gy, _ground_z(gx, gy) + rng.normal(0, 0.003, gx.size)], 1)]
    trees = []
    for x in [0.4, 1.5, 2.6, 3.9]:
        y = rng.normal(0, 0.02)
        c = np.array([x, y, float(_ground_z(np.array(x), np.array(y)))])
        r = rng.uniform(0.03, 0.045)
        pts.append(_shell(rng, c, r, -0.02, 0.7, 2500, taper=-0.01))
        pts.append(_shell(rng, c + [0, 0, 0.7], 0.012, 0.0, 1.5, 600))  # the leader
        for _ in range(12):  # canopy: leaf clusters on branches from 0.65 m up
            pts.append(_blob(rng, c + [rng.uniform(-0.5, 0.5), rng.uniform(-0.4, 0.3), rng.uniform(0.65, 2.2)],
                             0.08, 300))
        trees.append((c, r))
    post = np.array([4.9, 0.0, float(_ground_z(np.array(4.9), np.array(0.0)))])
    pts.append(_shell(rng, post, 0.05, -0.02, 2.5, 6000))
    for x in rng.uniform(0, 4.5, 6):  # weeds up to 0.35 m, leaves hanging low
        pts.append(_blob(rng, np.array([x, rng.uniform(-0.5, 0.1), 0.15]), np.array([0.07, 0.07, 0.08]), 300))
    poses = []
    for x in np.linspace(-0.5, 5.0, 60):
        z_cam, y_opt = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0])
        R = np.stack([np.cross(y_opt, z_cam), y_opt, z_cam], 1)
        poses.append(make_transform(R, np.array([x, -1.3, 1.0])))
    return np.vstack(pts), np.array(poses), trees, post


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_trunks_are_found_and_the_post_is_told_apart(seed):
    points, poses, trees, post = _side_cloud(seed)
    cands = find_trunk_candidates(points, poses)
    posts = [c for c in cands if c.post_like]
    trunks = sorted((c for c in cands if not c.post_like), key=lambda c: c.base[0])
    assert all(c.tree_like for c in trunks) and not posts[0].tree_like
    assert len(posts) == 1 and np.linalg.norm(posts[0].base[:2] - post[:2]) < 0.02
    assert len(trunks) == len(trees)  # no weed, leaf cluster or canopy taken for a trunk
    for c, (centre, r) in zip(trunks, trees, strict=True):
        assert np.linalg.norm(c.base[:2] - centre[:2]) < 0.015  # m, the axis at the ground
        assert abs(c.base[2] - centre[2]) < 0.03  # m, the ground under it
        assert abs(c.radius_m - (r - 0.01 * 0.31)) < 0.004  # m, the band's mean radius (tapering trunk)
        assert np.degrees(np.arccos(abs(c.axis[2]))) < 5.0
        assert abs(c.lateral_m - 1.3) < 0.1


def test_columns_the_detector_found_are_left_to_it_and_only_the_row_line_is_kept():
    points, poses, trees, _ = _side_cloud(0)
    cands = find_trunk_candidates(points, poses)
    # the detector saw trees 0 and 1 in four frames each
    detected = np.array([trees[i][0] + [0, -trees[i][1], 0.3] for i in (0, 1) for _ in range(4)])
    todo = columns_to_model(cands, detected, min_detections=3, radius_m=0.25, only=False)
    assert sorted(round(float(c.base[0]), 1) for c in todo) == [2.6, 3.9]
    assert len(columns_to_model(cands, detected, 3, 0.25, only=True)) == 4
    # a column 0.6 m off the row line (a stake by the cameras' path) is not a tree of the row
    off = TrunkCandidate(np.array([3.0, -0.6, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]), 0.03,
                         0.8, 180.0, 0.002, 300, False, True, 0.7)
    assert not any(c is off for c in columns_to_model(cands + [off], detected, 3, 0.25, only=True))


def test_a_column_makes_a_mask_of_its_depth_pixels_in_a_keyframe():
    """A 4 cm trunk 1.2 m in front of the camera, on a flat ground, rendered as depth: the mask holds the trunk's
    pixels between 5 cm and 0.9 m above the ground, not the ground or the wall behind."""
    cand = TrunkCandidate(np.array([0.0, 1.2, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.0]), 0.04,
                          1.5, 180.0, 0.002, 500, False, True, 1.2)
    z_cam, y_opt = np.array([0.0, 1.0, 0.0]), np.array([0.0, 0.0, -1.0])
    T = make_transform(np.stack([np.cross(y_opt, z_cam), y_opt, z_cam], 1), np.array([0.0, 0.0, 0.6]))
    u, v = np.meshgrid(np.arange(640.0), np.arange(480.0))
    d = np.stack([(u - INTR.cx) / INTR.fx, (v - INTR.cy) / INTR.fy, np.ones_like(u)], -1) @ T[:3, :3].T  # rays
    o = T[:3, 3]
    t_ground = np.where(d[..., 2] < -1e-6, -o[2] / np.minimum(d[..., 2], -1e-6), np.inf)
    t_wall = np.where(d[..., 1] > 1e-6, (3.0 - o[1]) / np.maximum(d[..., 1], 1e-6), np.inf)
    a = d[..., 0] ** 2 + (d[..., 1]) ** 2  # ray vs the vertical cylinder x^2 + (y - 1.2)^2 = r^2
    b = 2 * (d[..., 0] * o[0] + d[..., 1] * (o[1] - 1.2))
    cc = o[0] ** 2 + (o[1] - 1.2) ** 2 - 0.04 ** 2
    disc = b * b - 4 * a * cc
    t_cyl = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    t = np.minimum(np.minimum(t_ground, t_wall), t_cyl)
    depth = (t * 1.0).astype(np.float32)  # rays have z = 1 in the camera: t is the depth
    truth = (t_cyl <= np.minimum(t_ground, t_wall)) & np.isfinite(t_cyl)
    hz = o[2] + t * d[..., 2]
    truth &= (hz > 0.05) & (hz < 0.9)
    mask = cylinder_mask(cand, depth, T, INTR, 0.004, 0.9)
    assert mask is not None
    iou = (mask & truth).sum() / (mask | truth).sum()
    assert iou > 0.85
    dets = column_detections([cand], depth, T, INTR, 0.004, 150, 3.0)
    assert len(dets) == 1 and dets[0].source == "geometry" and dets[0].class_id == CLASS_TRUNK


def test_a_detection_on_a_tapering_column_is_on_a_tree_and_one_on_the_post_is_not():
    points, poses, trees, post = _side_cloud(1)
    cands = find_trunk_candidates(points, poses)
    for centre, r in trees:  # the face of each trunk towards the cameras, at 0.4 m
        assert on_tree_column(centre + [0.0, -r, 0.4], cands)
    assert not on_tree_column(post + [0.0, -0.05, 0.4], cands)
    assert not on_tree_column(trees[0][0] + [0.3, -0.3, 0.4], cands)  # a hand's width off: a post beside it
    assert not on_tree_column(None, cands)
    assert on_tree_column(post + [0.0, -0.05, 0.4], cands, post_like=True)  # the post, asked for posts
    assert not on_tree_column(trees[1][0] + [0.0, -trees[1][1], 0.4], cands, post_like=True)


def test_the_row_line_is_drawn_in_the_map_not_from_a_wandering_camera():
    """Columns on one straight row whose distances from a wandering camera path read 1.26-1.64 m are all on the
    row line; a stake 0.6 m across from it is not, whatever its distance from the cameras."""
    up = np.array([0.0, 0.0, 1.0])

    def column(x: float, y: float, lateral: float) -> TrunkCandidate:
        return TrunkCandidate(np.array([x, y, 0.02 * x]), up, up, 0.02, 1.5, 180.0, 0.003, 300, False, True, lateral)

    row = [column(x, 0.01 * np.sin(x), lat) for x, lat in [(0.0, 1.30), (1.1, 1.64), (2.3, 1.60), (3.4, 1.26),
                                                           (4.5, 1.29), (5.6, 1.62)]]
    stake = column(2.8, -0.6, 1.3)
    detected = np.array([row[i].base + [0.0, 0.0, 0.3] for i in (1, 2) for _ in range(4)])  # the detector's two
    todo = columns_to_model(row + [stake], detected, min_detections=3, radius_m=0.25, only=False)
    assert sorted(c.base[0] for c in todo) == [0.0, 3.4, 4.5, 5.6]
