"""Canonical frame of one side (paper, "Initial Alignment using Global Features", step 1: the ground plane
gives Y, the cloud's principal direction on it the row X, Z = X x Y the depth), and the grid thinning that
the alignment's steps share.

Frames: points and poses in the side's odom frame; metres.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from orchard_mapping.core.alignment_types import AlignmentParams, CanonicalFrame
from orchard_mapping.core.geometry import make_transform
from orchard_mapping.core.ground import GroundParams, fit_local_ground
from orchard_mapping.errors import AlignmentError

# --------------------------------------------------------------------------- canonical frame

def first_per_cell(points: np.ndarray, cell: float) -> np.ndarray:
    """Indices (sorted) of one point (the first) per occupied cell of a `cell` grid; points (N, D).

    Cells are keyed by one int64 (np.unique over rows of a 2D array took 4.3 of 5.6 s on 10 trees)."""
    keys = np.floor(points / cell).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = np.zeros(len(points), np.int64)
    for d in range(points.shape[1]):
        flat = flat * int(span[d]) + keys[:, d]
    n = len(points)
    if float(np.prod(span.astype(float))) <= max(4.0 * n, 2.0**20):
        # A dense grid: the lowest index per cell without sorting the keys (0.03 vs 0.21 s on 0.9 M points)
        first = np.full(int(np.prod(span)), n, np.int64)
        np.minimum.at(first, flat, np.arange(n))
        return np.sort(first[first < n])
    _, first = np.unique(flat, return_index=True)
    return np.sort(first)


def thin_to_grid(points: np.ndarray, cell: float) -> np.ndarray:
    """(Q, 3) one point (the first) per occupied cell of a `cell` grid."""
    return points[first_per_cell(points, cell)]


# points (at the front view's cells) a side's ground plane and row direction are fitted from, at most: a random
# subset of longer rows' (a 30-tree side has 0.28 M; 100 tiled trees 0.9 M took 3.4x as long)
CANONICAL_MAX_POINTS = 400_000


def canonical_frame(points: np.ndarray, poses: np.ndarray, side: str, params: AlignmentParams,
                    rng: np.random.Generator) -> CanonicalFrame:
    """The side's canonical frame (module docstring, step 1); points (P, 3) and poses (K, 4, 4) in odom.

    Each side's whole ground tilts its own way across the row (it is mostly the strip nearer that
    side's cameras): on the 10-tree standard row the two planes differ by 3.7 deg, and fitting only
    the strip along the trunks made it 8.4 deg (little ground is seen under the canopy). The initial
    transform (core.merge) removes what is left, from the trunk axes and local grounds.
    """
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 100:
        raise AlignmentError(f"{side}: a cloud of at least 100 points (P, 3) is needed, got {pts.shape}")
    poses = np.asarray(poses, float)
    if poses.ndim != 3 or len(poses) < 2:
        raise AlignmentError(f"{side}: at least two camera poses are needed")
    up0 = -poses[:, :3, 1].mean(axis=0)  # cameras' mean up (optical y points down)
    up0 /= np.linalg.norm(up0)
    if len(pts) > CANONICAL_MAX_POINTS:  # a plane and a principal direction need no more: the cost stays flat
        pts = pts[np.sort(rng.choice(len(pts), CANONICAL_MAX_POINTS, replace=False))]
    thin = thin_to_grid(pts, params.voxel_m)
    cam = poses[:, :3, 3]
    # Ground candidates: below the cameras (the canopy above them is never ground).
    below = thin[(thin - cam.mean(axis=0)) @ up0 < 0.0]
    # A whole side's ground undulates more than one tree's: a wider inlier band and more ground below
    # the plane tolerated than for a local ground (with 3 cm / 5 %, a flat row's back side found none);
    # one plane refitted over the whole side (a quadratic surface would bend with a long row's ground).
    gp = GroundParams(radius_m=1e9, max_height_above_trunk_bottom_m=1e9, inlier_threshold_m=0.05,
                      max_axis_angle_deg=params.ground_max_tilt_deg, max_below_fraction=0.2, iterations=500,
                      min_points=50, refine_surface="plane", refine_band_m=0.08, refine_iterations=5,
                      min_support_m2=0.0, wide_radius_m=0.0)
    fit = fit_local_ground(below, up0, cam.mean(axis=0), gp, rng)
    if fit is None:
        # One plane over a whole steep, undulating side leaves more of the ground below it: on slope_weeds
        # seed 2 (10 trees) no plane had at most 20 % below, with 40 % one was found 17.9 deg from the
        # cameras' up. Tried only where the first fit fails, so the sides that found a plane keep theirs.
        fit = fit_local_ground(below, up0, cam.mean(axis=0), replace(gp, max_below_fraction=0.4), rng)
    if fit is None:
        raise AlignmentError(f"{side}: no ground plane found within {params.ground_max_tilt_deg:g} deg "
                             f"of the cameras' up ({len(below)} candidate points)")
    Y = fit.normal / np.linalg.norm(fit.normal)
    above = thin[thin @ Y + fit.offset > params.ground_clearance_m]
    flat = above - np.outer(above @ Y, Y)  # on the ground plane
    flat -= flat.mean(axis=0)
    _, _, Vt = np.linalg.svd(flat[rng.choice(len(flat), min(len(flat), 20000), replace=False)],
                             full_matrices=False)
    X = Vt[0] - (Vt[0] @ Y) * Y
    X /= np.linalg.norm(X)
    view = poses[:, :3, 2].mean(axis=0)  # cameras' mean optical axis
    view -= (view @ Y) * Y
    if np.linalg.norm(view) < 1e-6:
        raise AlignmentError(f"{side}: the cameras look straight down or up: no depth direction")
    z_target = view if side == "front" else -view
    if np.cross(X, Y) @ z_target < 0:
        X = -X
    Z = np.cross(X, Y)
    R = np.stack([X, Y, Z])  # (3, 3) canonical <- odom
    c = cam.mean(axis=0)
    t = -R @ c
    t[1] = fit.offset  # height above the ground plane: Y . p + d
    return CanonicalFrame(make_transform(R, t), fit.inliers, fit.rmse_m)


VOXEL_CHUNK_POINTS = 300_000  # points per chunk of voxel_centres


def voxel_centres(points: np.ndarray, cell: float) -> np.ndarray:
    """(Q, 3) the centroid of each occupied cell of a `cell` grid: Open3D's voxel_down_sample, 2.2x
    faster than thin_to_grid on the 30-tree row's 2.9 M points (0.35 vs 0.79 s).

    In chunks of VOXEL_CHUNK_POINTS consecutive points when the cloud is ordered along space (a side's
    fused cloud comes in segments along the path, each sorted by x): the hash table then stays small, 2.5x
    faster on a 100-tree row's 9.6 M points (0.62 vs 1.58 s) and as fast per point as on 30 trees (one
    table over all grew 3.6x for 3.3x the points). A cell cut by a chunk's edge gives two centroids (4-7 %
    more on the 30-tree sides); every step after thins again (to the front view's cells, or coarser), so
    they count once. A cloud in no spatial order is taken whole."""
    import open3d as o3d

    def centres(chunk: np.ndarray) -> np.ndarray:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(chunk, np.float64)))
        return np.asarray(pc.voxel_down_sample(cell).points)

    n = len(points)
    if n <= 2 * VOXEL_CHUNK_POINTS:
        return centres(points)
    starts = np.arange(0, n, VOXEL_CHUNK_POINTS)
    lo, hi = np.minimum.reduceat(points, starts, axis=0), np.maximum.reduceat(points, starts, axis=0)  # (C, 3)
    # Ordered: along some axis the chunks each span at most half of the cloud on average (a 30-tree side's
    # fused cloud, in segments along the path: 0.28; shuffled: 1.0).
    if not np.any((hi - lo).sum(axis=0) <= 0.5 * len(starts) * (hi.max(axis=0) - lo.min(axis=0))):
        return centres(points)
    return np.concatenate([centres(points[i:i + VOXEL_CHUNK_POINTS]) for i in starts])
