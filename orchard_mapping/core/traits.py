"""The traits stage on a merged row cloud: ground and posts out, trees segmented, height and canopy volume.

`measure_row` runs the steps of core.segmentation and core.canopy with the settings of `TraitsParams`.
Frames: map, metres.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from orchard_mapping.core.canopy import (
    canopy_base_height,
    canopy_volume,
    main_body,
    mirrored_share,
    tree_height,
    voxel_downsample,
)
from orchard_mapping.core.segmentation import (
    cutting_plane_segmentation,
    ground_and_post_masks,
    height_above_grounds,
    row_axes,
    row_line_mask,
    shrink_and_expand_segmentation,
)
from orchard_mapping.errors import OrchardMappingError

__all__ = ["RowTraits", "TraitsError", "TraitsParams", "TreeMorphology", "measure_row"]

KIND_TREE, KIND_GROUND, KIND_POST, KIND_NONE, KIND_WIRE = 0, 1, 2, 3, 4  # per-point class codes of RowTraits.kind


VOLUME_THREADS = 2  # the crowns' alpha complexes run on this many threads


class TraitsError(OrchardMappingError, ValueError):
    """Invalid traits settings or inputs."""


@dataclass(frozen=True)
class TraitsParams:
    """Settings of the traits stage (config section `traits`)."""

    __pydantic_config__ = {"extra": "forbid"}  # config files: unknown keys are errors

    # m, alpha of the canopy volume: the paper's and the simulator's ground-truth definition (0.8 m)
    alpha_m: float = 0.8
    # m, points less than this above their tree's local ground plane are ground. 5 cm: ~5 sd of a fused
    # ground at 1.5-2 m (~1 cm) with margin for a plane tilt error of 1 deg over 0.5 m (0.9 cm); it only
    # cuts the trunk's first 5 cm, which neither height nor canopy volume uses.
    ground_margin_m: float = 0.05
    # m, points within post radius + this of a post axis are the post's (post radius fit errors ~1 cm)
    post_margin_m: float = 0.03
    # Tree top: the highest point with at least height_min_support others within height_support_radius_m.
    # Synthetic trees (test_canopy.py, ~20k crown surface points, 10 flying points 0.3-1 m above, level and
    # tilted ground): the raw maximum is off by > 0.25 m, this within 2 cm. Not yet measured on rendered rows.
    height_support_radius_m: float = 0.03
    height_min_support: int = 3
    # m, cells of the tree's main body (canopy.main_body): its height is measured on that body only. 5 cm
    # joins leaves and twigs of one crown (a 2 cm grid split crowns apart), and keeps a wire stub 10 cm off
    # a crown apart.
    body_cell_m: float = 0.05
    # m, voxel downsampling of the merged cloud before segmentation and volume (0 = off): the grid step of
    # the segmentation anyway; its effect on the volume is not yet separated from segmentation errors.
    voxel_m: float = 0.02
    # m, the crown is thinned further to this before its alpha complex (the Delaunay is the stage's main cost:
    # 0.9 s a crown at 2 cm, 0.6 s at 3 cm, 0.16 s at 4 cm). Each voxel's mean sits inside the crown's outer
    # leaves, so coarser voxels shrink the crown: 10-tree standard row seed 31, volume bias -2.3 / -3.9 / -5.2 %
    # at 2 / 3 / 4 cm (MAPE 3.6 / 4.5 / 5.4 %); 3 cm with the crowns on two threads keeps the stage's time.
    volume_voxel_m: float = 0.03
    # m, floor of the shrink-and-expand grid step (the median nearest-neighbour spacing of the pair's
    # points, the paper's choice); the grid's cells grow 8x per halving of the step.
    grid_min_m: float = 0.02
    # grid steps of morphological closing before the fill (bridges gaps between leaves). 0 left holes that
    # split the canopies at the first layers (synthetic 3-tree interlocking rows, seeds 0-3: 85-98 % per-point
    # accuracy instead of 97-99 %).
    close_voxels: int = 1
    # regions of the shrink smaller than this share of the largest are dropped (the paper's 10 %)
    min_region_fraction: float = 0.1
    # cutting_planes: on the simulator's 10-tree rows (touching crowns) its volumes were as good or better
    # (MAPE 4.6 / 3.5 % against 4.4 / 4.7 %) in half the time (benchmarks/traits_rows.py, docs/traits.md);
    # shrink_and_expand wins where a branch reaches over the neighbour (synthetic rows, 99 % vs 96-97 %)
    segmentation: Literal["shrink_and_expand", "cutting_planes"] = "cutting_planes"
    # m, points further than this along the row beyond the end trunks, or across the row from their trunk,
    # belong to no tree (canopies reach ~0.6 m; neighbouring rows start ~1.5 m away)
    max_reach_m: float = 1.0
    max_lateral_m: float = 1.2
    # m, trellis wires are looked for above this (segmentation.row_line_mask): the ground and low weeds form
    # lines along the row too; trellis wires run at 0.5 m and up (the simulator's at 0.9, 1.5, 2.1 m)
    wire_min_height_m: float = 0.3
    # where leaves hide a wire, its points are those within this x the noise of its shown stretches of the
    # line through them (segmentation.row_line_mask; 0: every point of the 6 cm block round it)
    wire_tube_factor: float = 1.5
    # m: a neighbour's points within this of the mirror image of a tree's far half count in that tree's canopy
    # volume too (core.canopy.mirrored_share; 0: off): where crowns interlock each tree's alpha shape holds the
    # shared leaves, which a split of the points gives to one tree only.
    share_reach_m: float = 0.05

    def __post_init__(self) -> None:
        for name in ("alpha_m", "grid_min_m", "body_cell_m"):
            if not getattr(self, name) > 0:
                raise TraitsError(f"traits.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("ground_margin_m", "post_margin_m", "height_support_radius_m", "voxel_m", "max_reach_m",
                     "max_lateral_m", "wire_min_height_m", "share_reach_m", "wire_tube_factor"):
            if not getattr(self, name) >= 0:
                raise TraitsError(f"traits.{name} must be >= 0, got {getattr(self, name)!r}")
        if self.height_min_support < 0 or self.close_voxels < 0:
            raise TraitsError("traits.height_min_support and traits.close_voxels must be >= 0")
        if not 0.0 <= self.min_region_fraction < 1.0:
            raise TraitsError(f"traits.min_region_fraction must be in [0, 1), got {self.min_region_fraction!r}")
        if self.segmentation not in ("shrink_and_expand", "cutting_planes"):
            raise TraitsError(f"traits.segmentation must be shrink_and_expand or cutting_planes, "
                              f"got {self.segmentation!r}")


@dataclass(frozen=True)
class TreeMorphology:
    tree: int  # index into the trunk arrays
    height_m: float  # m, local ground to top along the ground normal; nan without points
    canopy_volume_m3: float  # m^3, alpha-complex volume above the clear trunk
    n_points: int  # points of the tree (input cloud)
    clear_height_m: float  # m, where its canopy begins (given, or from its points); nan unknown
    separated: bool  # shrink-and-expand split both neighbouring pairs (True for cutting planes)
    # m, the height of each side's points of the tree alone (point_sides codes 0, 1); nan where that side has none
    height_by_side: tuple[float, float] = (float("nan"), float("nan"))


@dataclass(frozen=True)
class RowTraits:
    tree: np.ndarray  # (N,) int, tree index of each input point, -1 none (ground, post, out of reach)
    kind: np.ndarray  # (N,) int8, KIND_TREE / KIND_GROUND / KIND_POST / KIND_WIRE / KIND_NONE
    trees: tuple[TreeMorphology, ...]


def measure_row(points: np.ndarray, trunk_positions: np.ndarray, ground_points: np.ndarray,
                ground_normals: np.ndarray, clear_heights: np.ndarray, row_direction: np.ndarray,
                params: TraitsParams, *, post_points: np.ndarray | None = None,
                post_radius_m: float = 0.0, trunk_radii: np.ndarray | None = None,
                point_sides: np.ndarray | None = None) -> RowTraits:
    """Traits of every tree of a merged row: points (N, 3); per tree (T): trunk_positions (T, 3), the point of
    each trunk's line the row is split at (the cutting planes and the shrink's trunk lines pass through it:
    where the axis meets the ground, or, for leaning trees, the axis at crown height), the local ground planes (ground_points (T, 3), unit-up
    ground_normals (T, 3)), clear trunk heights (T,) m (NaN: where the tree's own points say the canopy
    begins, core.canopy.canopy_base_height, off its trunk of radius trunk_radii (T,) m); the row direction
    (3,); vertical posts standing on post_points (P, 3) with radius post_radius_m; point_sides (N,) 0 / 1: the
    side each point came from (each tree's height is then also measured on each side's points alone)."""
    pts = np.asarray(points, float)
    tr = np.asarray(trunk_positions, float).reshape(-1, 3)
    gp = np.asarray(ground_points, float).reshape(-1, 3)
    gn = np.asarray(ground_normals, float).reshape(-1, 3)
    clear = np.asarray(clear_heights, float).reshape(-1)
    if not (len(tr) == len(gp) == len(gn) == len(clear)) or len(tr) == 0:
        raise TraitsError(f"per-tree inputs must have the same length >= 1: trunks {len(tr)}, ground points "
                          f"{len(gp)}, normals {len(gn)}, clear heights {len(clear)}")
    up = gn.mean(axis=0)
    cen, inv = voxel_downsample(pts, params.voxel_m)  # (V, 3), (N,)
    cut = cutting_plane_segmentation(cen, tr, row_direction, up=up)
    height = height_above_grounds(cen, cut, gp, gn)  # (V,) m
    ground, post = ground_and_post_masks(cen, cut, gp, gn, ground_margin_m=params.ground_margin_m,
                                         post_points=post_points, post_radius_m=post_radius_m,
                                         post_margin_m=params.post_margin_m, height=height)
    # the trellis wires: lines along the row at one height and depth (in a frame of the row: x along, z up)
    axes = row_axes(row_direction, up)  # (3, 3) rows: along the row (level), across, up
    wire = row_line_mask(cen @ axes.T, height, min_height_m=params.wire_min_height_m,
                         tube_factor=params.wire_tube_factor) & ~ground & ~post
    keep = np.flatnonzero(~ground & ~post & ~wire)
    tree_v = np.full(len(cen), -1)
    separated = np.ones(max(len(tr) - 1, 0), bool)
    if params.segmentation == "shrink_and_expand" and len(tr) > 1:
        seg = shrink_and_expand_segmentation(cen[keep], tr, row_direction, up=up, min_grid_m=params.grid_min_m,
                                             close_voxels=params.close_voxels,
                                             min_region_fraction=params.min_region_fraction,
                                             max_reach_m=params.max_reach_m, max_lateral_m=params.max_lateral_m)
        tree_v[keep] = seg.tree
        separated = np.zeros_like(separated)
        separated[:] = seg.pair_separated
        rank = np.empty(len(tr), int)
        rank[seg.order] = np.arange(len(tr))
    else:
        tree_v[keep] = cutting_plane_segmentation(cen[keep], tr, row_direction, up=up,
                                                  max_reach_m=params.max_reach_m, max_lateral_m=params.max_lateral_m)
        rank = np.arange(len(tr))
    kind_v = np.where(ground, KIND_GROUND, np.where(post, KIND_POST, np.where(
        wire, KIND_WIRE, np.where(tree_v >= 0, KIND_TREE, KIND_NONE))))
    tree = tree_v[inv]
    out: list[TreeMorphology] = []
    crowns: list[np.ndarray] = []
    along_order = np.argsort(tr @ axes[0])  # (T,) trees in row order
    place = np.empty(len(tr), int)
    place[along_order] = np.arange(len(tr))
    for t in range(len(tr)):
        mine = tree == t
        n_pts = int(mine.sum())
        in_body = main_body(pts[mine], params.body_cell_m) if n_pts else np.zeros(0, bool)
        body = pts[mine][in_body]

        def height_of(p: np.ndarray, t: int = t) -> float:
            return tree_height(p, gp[t], gn[t], support_radius_m=params.height_support_radius_m,
                               min_support=params.height_min_support) if len(p) else float("nan")

        h = height_of(body)
        by_side = (float("nan"), float("nan"))
        if point_sides is not None and n_pts:
            body_side = np.asarray(point_sides)[mine][in_body]
            by_side = (height_of(body[body_side == 0]), height_of(body[body_side == 1]))
        c = float(clear[t])
        mine_v = cen[tree_v == t]  # (M, 3) the tree's voxels
        if not np.isfinite(c) and n_pts:
            r = float(trunk_radii[t]) if trunk_radii is not None else 0.0
            c = canopy_base_height(mine_v, gp[t], gn[t], trunk_radius_m=r, body_cell_m=params.body_cell_m)
        k = rank[t]
        sep = bool((k == 0 or separated[k - 1]) and (k == len(tr) - 1 or separated[k]))
        out.append(TreeMorphology(t, h, float("nan"), n_pts, c, sep, by_side))
        neighbours = [cen[tree_v == along_order[place[t] + k]] for k in (-1, 1) if 0 <= place[t] + k < len(tr)]
        shared = [nb[mirrored_share(mine_v, nb, tr[t], axes[0], params.share_reach_m)] for nb in neighbours]
        crowns.append(np.concatenate([mine_v, *shared]))

    def volume(m: TreeMorphology) -> float:
        if not np.isfinite(m.clear_height_m):
            return float("nan")
        return canopy_volume(crowns[m.tree], gp[m.tree], gn[m.tree], clear_trunk_height_m=m.clear_height_m,
                             alpha_m=params.alpha_m, body_cell_m=params.body_cell_m,
                             voxel_m=params.volume_voxel_m if params.volume_voxel_m > params.voxel_m else 0.0)

    # the crowns' Delaunay (qhull lets go of the GIL) on two threads: each tree's volume is its own, so the
    # result is the same on any number; 10 crowns of 3 cm voxels on 2 busy cores: 15.0 s on one, 10.3 s on two
    with ThreadPoolExecutor(max_workers=VOLUME_THREADS) as pool:
        volumes = list(pool.map(volume, out))
    out = [replace(m, canopy_volume_m3=v) for m, v in zip(out, volumes, strict=True)]
    return RowTraits(tree, kind_v[inv].astype(np.int8), tuple(out))
