"""Per-point segmentation score: each point of trees.laz against the tree whose surface it lies on.

The simulator writes the row's surfaces as points labelled with their tree, or -1 for ground, posts, wires
and weeds (`tree_surfaces.npz`). A result point whose nearest surface sample (within `tolerance_m`) is a
tree's is that tree's point in truth; it is right when the product gave it to the result tree matched with
that true tree (the evaluator's tree matching). Points nearest no tree surface are left out of the accuracy
and counted apart: what share of the points given to a tree lie on no tree at all.

The accuracy near a neighbour is the same score over the points whose true tree has another tree's surface
within `near_neighbour_m`: where the crowns touch, which is where the segmentation methods differ.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from orchard_mapping.errors import ResultFormatError

TREE_SURFACES_NPZ = "tree_surfaces.npz"  # written by the simulator beside ground_truth.json
# A leaf's corner or centre is within ~4 cm of any point on it (leaves 5-8 cm); the fused cloud adds ~1 cm
# and the wind scenario's sway a few more: 5 cm keeps a reconstructed leaf on its own tree's samples.
SURFACE_TOLERANCE_M = 0.05
NEAR_NEIGHBOUR_M = 0.3  # "where the crowns touch": another tree's surface this close


@dataclass(frozen=True)
class SegmentationScore:
    """Per-point tree labels of trees.laz against the true trees' surfaces (matched trees only)."""

    n_points: int  # result points within tolerance of a matched true tree's surface
    accuracy: float  # share of them the product gave to the matched result tree
    n_near_neighbour: int
    accuracy_near_neighbour: float | None  # the same over points with another tree's surface within 0.3 m
    unassigned: float  # share of the tree points the product gave to no tree (ground, post, none)
    off_tree: float  # share of the points given to a tree that lie near no tree surface
    tolerance_m: float


def load_tree_surfaces(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) world points and (N,) tree ids (-1 not a tree) of a tree_surfaces.npz; ResultFormatError if
    unusable."""
    path = Path(path)
    try:
        with np.load(path) as z:
            pts, tree = np.asarray(z["points"], float), np.asarray(z["tree"], np.int64)
    except (OSError, KeyError, ValueError) as err:
        raise ResultFormatError(f"{path}: not a tree surfaces file ({err})") from err
    if pts.ndim != 2 or pts.shape[1:] != (3,) or tree.shape != (len(pts),):
        raise ResultFormatError(f"{path}: points {pts.shape} and tree {tree.shape} do not pair")
    return pts, tree


def segmentation_score(points_map: np.ndarray, result_tree: np.ndarray, surfaces_world: np.ndarray,
                       surface_tree: np.ndarray, T_map_world: np.ndarray, true_to_result: dict[int, int],
                       tolerance_m: float = SURFACE_TOLERANCE_M,
                       near_neighbour_m: float = NEAR_NEIGHBOUR_M) -> SegmentationScore:
    """Score result points (N, 3, map) labelled with result tree ids (N,; -1 none) against the true surfaces
    (M, 3, world) and their tree ids (M,). `true_to_result`: the tree matching (true id -> result id)."""
    R, t = T_map_world[:3, :3], T_map_world[:3, 3]
    surf = surfaces_world @ R.T + t  # (M, 3) map
    d, k = cKDTree(surf).query(points_map, k=1, distance_upper_bound=tolerance_m)  # (N,), (N,)
    near_any = np.isfinite(d)
    true_of = np.full(len(points_map), -1, np.int64)
    true_of[near_any] = surface_tree[k[near_any]]  # -1: nearest surface is not a tree's
    on_tree = true_of >= 0
    matched = np.isin(true_of, np.fromiter(true_to_result, np.int64, len(true_to_result)))
    want = np.array([true_to_result.get(int(x), -2) for x in true_of[matched]], np.int64)  # (n,)
    got = result_tree[matched]
    right = got == want
    # points whose true tree has another tree's surface near: distance to the nearest other tree's sample
    near = np.zeros(int(matched.sum()), bool)
    pm, tm = points_map[matched], true_of[matched]
    for tid in np.unique(tm):
        others = surf[(surface_tree >= 0) & (surface_tree != tid)]
        if len(others):
            sel = tm == tid
            dn, _ = cKDTree(others).query(pm[sel], k=1, distance_upper_bound=near_neighbour_m)
            near[sel] = np.isfinite(dn)
    given = result_tree >= 0
    n = int(matched.sum())
    return SegmentationScore(
        n_points=n,
        accuracy=float(right.mean()) if n else float("nan"),
        n_near_neighbour=int(near.sum()),
        accuracy_near_neighbour=float(right[near].mean()) if near.any() else None,
        unassigned=float((got < 0).mean()) if n else float("nan"),
        off_tree=float((~on_tree[given]).mean()) if given.any() else float("nan"),
        tolerance_m=float(tolerance_m),
    )
