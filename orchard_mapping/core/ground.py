"""Local ground plane under one tree (paper: "Local Ground Plane").

The local ground of a tree is a plane n . p + d = 0 with n pointing up (away
from the ground), fitted to the side's fused points around the trunk base.
Plain RANSAC takes the plane with the most inliers, which near a tree is often
not the ground: a wall of leaves, a weed canopy, the trunk's own surface. The
paper changes RANSAC's degenerate condition with the trunk axis as a prior:

  - the plane normal must lie within `max_axis_angle_deg` of the trunk axis;
  - the plane must be the lower boundary of the points along its normal: a
    candidate with more points further than the inlier threshold t_s below it
    than `max_below_fraction` of its inliers is rejected (a plane on weed tops
    or on a leaf layer has the true ground below it).

Real ground is not a plane (undulation, roughness), and the tree's local ground is the plane of the
terrain the side saw around it. So the RANSAC plane only seeds the ground *surface*: a quadratic surface
fitted to the lower-envelope cells (the lowest point of each 4 cm cell), cells more than `refine_band_m`
above it left out (weeds, leaves) and cells below kept (the ground is the lower boundary), iterated, then
grown cell by cell into neighbours that follow the ground beside them. The reported plane is the
least-squares plane through those ground cells (robustly trimmed); a plane with less than
`min_support_m2` of such ground is not reported (a glimpse of ground between weeds fixes no tilt). `fit_local_ground` does this; `fit_plane_plain_ransac` (Open3D's
`segment_plane`) is kept as the baseline the paper compares with. Frames: all
points and vectors in the side's reconstruction frame (odom_<side>), metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from orchard_mapping.core.cylinder import perpendicular_basis
from orchard_mapping.errors import OrchardMappingError

__all__ = [
    "GroundError",
    "GroundParams",
    "LocalGroundFit",
    "fit_local_ground",
    "fit_plane_plain_ransac",
    "ground_neighbourhood",
]


ENVELOPE_CELL_M = 0.04  # m, cells of the lower envelope (one point each: the lowest along the axis)
ROBUST_MIN_BAND_M = 0.01  # m, the trimming band of the ground cells' plane never narrower (noise, roughness)
# robust sd (MAD) a ground cell may lie off the ground cells' plane: 3 trimmed curved ground (a slope_weeds
# tree 0.6 -> 3.6 deg), no trimming let two weed cells tilt a narrow strip's plane by 5 deg
ROBUST_K = 5.0
# Mean-shift rounds of each ground cell's surface height (cell_surface_band_m) after the first window above
# its lowest sample (2 rounds gave the same planes as 1 on the slope_weeds grounds)
SURFACE_PASSES = 1
# The ground grows from the quadratic's cells into neighbours this close (m: ~2 cells and the diagonal),
# at most this many bands off the quadratic, in at most this many rounds.
GROW_RADIUS_M = 0.09
GROW_MAX_OFF_BANDS = 2.5
GROW_MAX_ROUNDS = 100


class GroundError(OrchardMappingError, ValueError):
    """A local ground cannot be fitted (too few points, bad prior)."""


@dataclass(frozen=True)
class GroundParams:
    """Settings of the local ground fit (config section `ground`)."""

    __pydantic_config__ = {"extra": "forbid"}  # config files: unknown keys are errors

    # m, horizontal radius around the trunk axis: the ground truth's own definition of a tree's local
    # ground is the plane of the terrain within 0.5 m of the trunk.
    radius_m: float = 0.5
    # m, points higher than this above the lowest trunk point are not ground candidates (canopy, upper trunk)
    max_height_above_trunk_bottom_m: float = 0.3
    inlier_threshold_m: float = 0.02  # m, t_s: point-to-plane distance of an inlier
    max_axis_angle_deg: float = 25.0  # deg, plane normal vs trunk axis (trunks lean up to ~10 deg)
    max_below_fraction: float = 0.05  # points further than t_s below the plane, as a share of its inliers
    # RANSAC samples. 300 left a wrong plane (ground strip + weed tops) winning for some random draws on
    # slope_weeds; 1000 costs ~8 ms more per tree (~19 ms a tree at ~5000 candidate points).
    iterations: int = 1000
    min_points: int = 50  # fewer candidate points: no ground for this tree
    # The ground surface the plane is refitted to (see the module docstring): "quadratic", or "plane" (the
    # earlier refit: least squares to the cells within refine_band_m of the plane itself). Measured on the
    # ground candidates the pipeline hands to this fit on slope_weeds rows (12 cm undulation, weeds to
    # 0.4 m), each refitted with several RANSAC seeds (benchmarks/ground.py), and on whole rows
    # (benchmarks/trunks.py): docs/ground.md.
    refine_surface: Literal["quadratic", "plane"] = "quadratic"
    # m: cells within this of the ground surface are ground. 2 cm is ~2 sd of the fused cloud's ground at
    # 1.5-2 m plus the terrain's roughness; 3 cm let weed tops into the surface (more planes off by > 5 deg
    # on the same data), 5 cm was the plane refit's band.
    refine_band_m: float = 0.02
    refine_iterations: int = 10
    # m^2 of ground cells (the plane's): less ground seen than this and the plane is not reported (a glimpse
    # of ground between weeds gives any tilt; slope_weeds seed 0: trees whose ground was seen over less
    # than ~10 % of the 0.5 m disk came out 15-39 deg off). 0.12: of the ground-surface fits on slope_weeds
    # and standard rows (benchmarks/ground.py) with 0.10-0.13 m^2, 1 of 4 was within 1 deg and 1 cm and
    # one was a plane up weed tops beside a strip of ground (34 deg); above 0.13 m^2 most are.
    min_support_m2: float = 0.12
    # m. The plane's height is that of the ground surface through its cells: per cell the mean of its
    # points within this of its lowest one, re-centred once (0: the lowest points themselves, which sat
    # 2.9 mm low in median on slope_weeds grounds: 1 cm gave +0.0 mm, 1.5 cm +0.5, benchmarks/ground.py).
    cell_surface_band_m: float = 0.01
    # m. A tree without a local ground still gets its diameter height from the ground over this wider
    # disk (flagged; 0 = off).
    wide_radius_m: float = 1.0

    def __post_init__(self) -> None:
        for name in ("radius_m", "inlier_threshold_m", "max_axis_angle_deg", "max_height_above_trunk_bottom_m",
                     "refine_band_m"):
            if not getattr(self, name) > 0:
                raise GroundError(f"ground.{name} must be > 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.max_below_fraction < 1.0:
            raise GroundError(f"ground.max_below_fraction must be in [0, 1), got {self.max_below_fraction!r}")
        if self.iterations < 1 or self.min_points < 3:
            raise GroundError("ground.iterations must be >= 1 and ground.min_points >= 3")
        if (self.refine_iterations < 0 or self.min_support_m2 < 0 or self.wide_radius_m < 0
                or not self.cell_surface_band_m >= 0):
            raise GroundError("ground.refine_iterations, ground.min_support_m2, ground.wide_radius_m and "
                              "ground.cell_surface_band_m must be >= 0")


@dataclass(frozen=True)
class LocalGroundFit:
    """A local ground plane n . p + d = 0 (odom_<side>, m)."""

    normal: np.ndarray  # (3,) unit, up (along the trunk axis prior)
    offset: float  # m, d
    point: np.ndarray  # (3,) m, a point on the plane: where the trunk axis meets it
    inliers: int  # points within t_s of the plane
    rmse_m: float  # m, RMS point-to-plane distance of the inliers
    candidates: int  # points the fit was chosen from
    support_m2: float = float("nan")  # m^2, ground area (lower-envelope cells) within refine_band_m of it
    # m, horizontal distance from `point` to the centre of that area. A plane seen only in a corner of the
    # disk is extrapolated to the trunk: its height there is off by about its tilt error times this
    # (10-tree rows: under 1 cm at 0.1-0.25 m, up to 5 cm at 0.4 m), which the merge weighs in.
    support_offset_m: float = float("nan")
    # (G, 3) m: the ground cells the plane was fitted to (one lower-envelope point each). What the plane
    # stands for: a side sees part of the disk, and over undulating ground the plane of that part is not the
    # plane of another part (benchmarks/ground.py scores the fit against the terrain over these cells too).
    ground_cells: np.ndarray | None = field(default=None, repr=False, compare=False)

    def height_of(self, p: np.ndarray) -> np.ndarray:
        """Signed height (m) of points (..., 3) above the plane."""
        return np.asarray(p, float) @ self.normal + self.offset


def ground_neighbourhood(points: np.ndarray, axis_point: np.ndarray, axis: np.ndarray, params: GroundParams,
                         trunk_bottom_height: float | None = None) -> np.ndarray:
    """Indices of the points that may be the tree's local ground.

    points (P, 3); axis_point (3,) a point on the trunk axis; axis (3,) unit, up. Candidates lie within
    radius_m of the axis and, when the lowest trunk point's height along the axis is known, at most
    max_height_above_trunk_bottom_m above it (the canopy and the upper trunk are never ground).
    """
    rel = np.asarray(points, float) - axis_point  # (P, 3)
    h = rel @ axis  # (P,) height along the axis
    radial = np.linalg.norm(rel - h[:, None] * axis, axis=1)  # (P,)
    keep = radial <= params.radius_m
    if trunk_bottom_height is not None:
        keep &= h <= trunk_bottom_height + params.max_height_above_trunk_bottom_m
    return np.flatnonzero(keep)


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    v = np.asarray(v, float).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n < 1e-9:
        raise GroundError(f"{what} must be a non-zero finite vector, got {v.tolist()}")
    return v / n


def _refine(points: np.ndarray, normal: np.ndarray, offset: float, t: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Least-squares plane (SVD) through the inliers of (normal, offset), keeping the normal's side."""
    inl = np.abs(points @ normal + offset) < t
    if inl.sum() < 3:
        return normal, offset, inl
    c = points[inl].mean(axis=0)
    _, _, vt = np.linalg.svd(points[inl] - c, full_matrices=False)
    n = vt[2] if vt[2] @ normal > 0 else -vt[2]
    return n, float(-n @ c), np.abs(points @ n - n @ c) < t


def _lower_envelope(pts: np.ndarray, up: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(indices (C,) of the lowest point along `up` of each cell_m square cell across `up`, the cell of each
    point (P,) as an index into them)."""
    e1, e2 = perpendicular_basis(up)
    cells = np.floor(np.stack([pts @ e1, pts @ e2], 1) / cell_m).astype(np.int64)  # (P, 2)
    order = np.lexsort((pts @ up, cells[:, 1], cells[:, 0]))  # by cell, then height
    c = cells[order]
    first = np.ones(len(order), bool)
    first[1:] = np.any(c[1:] != c[:-1], axis=1)
    label = np.empty(len(pts), np.int64)
    label[order] = np.cumsum(first) - 1
    return order[first], label


def _cell_surface(pts: np.ndarray, up: np.ndarray, lowest: np.ndarray, label: np.ndarray, band: float
                  ) -> np.ndarray:
    """(C, 3) per lower-envelope cell, where the ground surface runs through it rather than its lowest
    sample, which lies below the surface by the spread of the cell's samples (noise, roughness): the mean
    of its points within `band` above the lowest, then SURFACE_PASSES times the mean of those within `band`
    of that mean along `up` (a box-kernel mean shift: symmetric about the surface, so the truncation's
    bias goes; a weed stem above it stays out). Per cell, not about a plane: over undulating ground a
    window about one plane cuts the cells away from it (slope_weeds, measured: worse)."""
    h = pts @ up  # (P,)
    cells = len(lowest)
    centre = h[lowest]  # (C,) along up
    lo, hi = centre, centre + band
    for _ in range(SURFACE_PASSES + 1):
        near = (h >= lo[label]) & (h <= hi[label])  # (P,)
        count = np.bincount(label[near], minlength=cells).astype(float)  # (C,) >= 1 (the lowest itself)
        centre = np.bincount(label[near], weights=h[near], minlength=cells) / np.maximum(count, 1.0)
        lo, hi = centre - band, centre + band
    # The cell's point on the surface: its samples' mean across up, at the surface's height along up.
    near = (h >= lo[label]) & (h <= hi[label])
    count = np.maximum(np.bincount(label[near], minlength=cells).astype(float), 1.0)
    mean = np.stack([np.bincount(label[near], weights=pts[near, k], minlength=cells) for k in range(3)], 1)
    mean /= count[:, None]
    return mean + (centre - mean @ up)[:, None] * up


def _ground_cells(envelope: np.ndarray, n: np.ndarray, d0: float, origin: np.ndarray, band: float,
                  iterations: int) -> np.ndarray:
    """Which lower-envelope points (C, 3) lie on the ground surface grown from the plane (n, d0). Bool (C,).

    1. A quadratic height h(u, v) over the plane (u, v across n, about `origin`), refitted by least squares
       to the cells not more than `band` above it (cells below stay: the ground is the lower boundary);
       the cells within `band` of it are ground.
    2. Real ground is not quadratic over a metre (undulation, ruts): the ground grows cell by cell into the
       neighbouring cells (within GROW_RADIUS_M) whose height off the quadratic, refitted to the ground so
       far, is within `band` of their ground neighbours' and within GROW_MAX_OFF_BANDS x band of the
       quadratic. Weed tops stand off the ground next to them and are not reached. (Simulated undulating
       ground without weeds, 12 seeds: worst normal error 7.7 -> 2.5 deg; the slope_weeds rows alike.)
    """
    e1, e2 = perpendicular_basis(n)
    rel = envelope - origin
    u, v, h = rel @ e1, rel @ e2, envelope @ n + d0  # (C,) each
    A = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], 1)  # (C, 6)
    tree = cKDTree(np.stack([u, v], 1))
    near = tree.sparse_distance_matrix(tree, GROW_RADIUS_M, output_type="coo_matrix").tocsr()  # (C, C)
    near.data[:] = 1.0
    # The quadratic is fitted only where the plane found ground (and next to it): out there it is an
    # extrapolation that bends to reach weed tops.
    domain = (near @ (np.abs(h) < band).astype(float)) > 0  # (C,) the plane's cells and their neighbours
    coef = np.zeros(6)  # starts as the plane itself
    for _ in range(iterations):
        keep = domain & (h - A @ coef <= band)
        if np.count_nonzero(keep) < 2 * A.shape[1]:
            break
        coef = np.linalg.lstsq(A[keep], h[keep], rcond=None)[0]
    ground = domain & (np.abs(h - A @ coef) < band)
    if np.count_nonzero(ground) < 2 * A.shape[1]:
        return ground
    for _ in range(GROW_MAX_ROUNDS):
        coef = np.linalg.lstsq(A[ground], h[ground], rcond=None)[0]
        off = h - A @ coef  # (C,) height off the quadratic
        g = ground.astype(float)
        n_nb = near @ g  # ground neighbours per cell
        front = np.flatnonzero(~ground & (n_nb > 0))
        if not len(front):
            break
        expected = (near @ (off * g))[front] / n_nb[front]  # their ground neighbours' mean offset
        grow = front[(np.abs(off[front] - expected) < band) & (np.abs(off[front]) < GROW_MAX_OFF_BANDS * band)]
        if not len(grow):
            break
        ground[grow] = True
    return ground


def _plane_of_cells(envelope: np.ndarray, cells: np.ndarray, n: np.ndarray, d0: float, rounds: int = 3
                    ) -> tuple[np.ndarray, float, np.ndarray]:
    """The least-squares plane of the ground cells envelope[cells], without the cells off it by more than
    ROBUST_K robust sd (MAD): the quadratic surface can bend at the edge of a strip of ground to take in a
    weed cell or two, and across a narrow strip a few such cells tilt the plane (a slope_weeds tree: 3 weed
    cells among 152 tilted it 11 deg).
    Returns (normal, offset, the cells kept)."""
    keep = cells.copy()
    for _ in range(rounds):
        n, d0, _ = _refine(envelope[keep], n, d0, np.inf)
        r = envelope @ n + d0
        mad = float(np.median(np.abs(r[keep] - np.median(r[keep]))))
        new = cells & (np.abs(r) <= max(ROBUST_K * 1.4826 * mad, ROBUST_MIN_BAND_M))
        if np.count_nonzero(new) < 3 or np.array_equal(new, keep):
            break
        keep = new
    return n, d0, keep


def fit_local_ground(points: np.ndarray, axis: np.ndarray, axis_point: np.ndarray, params: GroundParams,
                     rng: np.random.Generator) -> LocalGroundFit | None:
    """RANSAC plane with the trunk-axis prior (paper: "Local Ground Plane"); None if no plane passes.

    points (P, 3) odom: the ground candidates (see `ground_neighbourhood`); axis (3,) trunk axis, up;
    axis_point (3,) a point on it (the plane's `point` is where this axis meets the plane).
    """
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise GroundError(f"ground points must have shape (P, 3), got {pts.shape}")
    up = _unit(axis, "the trunk axis prior")
    p_axis = np.asarray(axis_point, float).reshape(3)
    n_pts = len(pts)
    if n_pts < params.min_points:
        return None
    t = params.inlier_threshold_m
    cos_max = np.cos(np.radians(params.max_axis_angle_deg))
    # Samples come from the lower envelope (the lowest point of each 4 cm cell across the axis): the
    # ground is the lower boundary, and under weeds or a leaf wall it is a small share of all points
    # (6 % in the hidden-trunk test), which uniform sampling would rarely draw three times.
    pool, label = _lower_envelope(pts, up, ENVELOPE_CELL_M)
    idx = pool[rng.integers(0, len(pool), size=(params.iterations, 3))]  # (I, 3) samples
    a, b, c = pts[idx[:, 0]], pts[idx[:, 1]], pts[idx[:, 2]]  # (I, 3) each
    normals = np.cross(b - a, c - a)  # (I, 3)
    norms = np.linalg.norm(normals, axis=1)
    ok = norms > 1e-9
    normals[ok] /= norms[ok, None]
    normals *= np.sign(normals @ up)[:, None]  # up, along the prior
    ok &= normals @ up >= cos_max  # the prior: normal roughly along the trunk axis
    offsets = -np.einsum("ij,ij->i", normals, a)  # (I,)
    best: tuple[int, int] | None = None  # (inliers, candidate)
    for i in np.flatnonzero(ok):  # distances per candidate: (P,), candidates are few after the prior
        d = pts @ normals[i] + offsets[i]
        near = np.abs(d) < t
        # Not the lower boundary: ground lies below it. Counted against the plane's own support, not all
        # points: under weeds the ground may be a few percent of the candidates (a plane through weed
        # tops and a strip of ground then has more inliers than the ground and half the ground below it).
        if np.count_nonzero(d < -t) > params.max_below_fraction * np.count_nonzero(near):
            continue
        # Support is counted in area (lower-envelope cells), not in points: a dense wall of weeds or the
        # bottom edge of a leaf curtain holds many points in few cells, the ground few points in many.
        score = int(np.count_nonzero(near[pool]))
        if best is None or score > best[0]:
            best = (score, int(i))
    if best is None:
        return None
    envelope = pts[pool]  # (C, 3) one point per cell: area, not point density, weighs the refit
    n, d0 = normals[best[1]], float(offsets[best[1]])
    if params.refine_surface == "quadratic":
        on_plane = _ground_cells(envelope, n, d0, p_axis, params.refine_band_m, params.refine_iterations)
        if np.count_nonzero(on_plane) < 3:
            return None
        n, d0, on_plane = _plane_of_cells(envelope, on_plane, n, d0)
        if params.cell_surface_band_m > 0:
            # The plane's height from where the ground surface runs through its cells, not their lowest
            # samples (~1.5 noise sd below it); its tilt stays the lowest samples': refitted to the cells'
            # surface points instead, the normal came out worse on the slope_weeds grounds (docs/ground.md).
            surface = _cell_surface(pts, up, pool, label, params.cell_surface_band_m)
            d0 -= float(np.median((surface[on_plane] - envelope[on_plane]) @ n))
    else:
        n, d0, _ = _refine(pts, n, d0, t)
        for _ in range(params.refine_iterations):
            n, d0, _ = _refine(envelope, n, d0, params.refine_band_m)
        on_plane = np.abs(envelope @ n + d0) < params.refine_band_m
    support = float(np.count_nonzero(on_plane)) * ENVELOPE_CELL_M**2
    inl = np.abs(pts @ n + d0) < t
    if n @ up < cos_max or inl.sum() < 3 or support < params.min_support_m2:
        return None
    fit = _ground_fit(pts, inl, n, d0, up, p_axis, support)
    rel = envelope[on_plane].mean(axis=0) - fit.point
    return replace(fit, support_offset_m=float(np.linalg.norm(rel - (rel @ n) * n)), ground_cells=envelope[on_plane])


def _ground_fit(pts: np.ndarray, inliers: np.ndarray, n: np.ndarray, d0: float, up: np.ndarray,
                p_axis: np.ndarray, support_m2: float = float("nan")) -> LocalGroundFit:
    """The plane n . p + d0 = 0 with its fit statistics over pts[inliers]; its point is where the axis
    (p_axis, up) meets it (the foot of p_axis on the plane if the axis runs parallel to it)."""
    resid = pts[inliers] @ n + d0
    denom = float(up @ n)
    point = p_axis - (p_axis @ n + d0) * n if abs(denom) < 1e-6 else p_axis - (p_axis @ n + d0) / denom * up
    return LocalGroundFit(normal=n, offset=d0, point=point, inliers=int(len(resid)),
                          rmse_m=float(np.sqrt(np.mean(resid**2))) if len(resid) else float("nan"),
                          candidates=len(pts), support_m2=support_m2)


def fit_plane_plain_ransac(points: np.ndarray, params: GroundParams, seed: int, up_hint: np.ndarray,
                           axis_point: np.ndarray) -> LocalGroundFit | None:
    """The baseline: Open3D's plain RANSAC (most inliers wins, no prior), normal turned to `up_hint`."""
    import open3d as o3d

    pts = np.asarray(points, float)
    if len(pts) < params.min_points:
        return None
    o3d.utility.random.seed(int(seed))
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    model, inliers = pc.segment_plane(params.inlier_threshold_m, 3, params.iterations)
    n = np.asarray(model[:3], float)
    d0 = float(model[3]) / float(np.linalg.norm(n))
    n = n / np.linalg.norm(n)
    up = _unit(up_hint, "up_hint")
    if n @ up < 0:
        n, d0 = -n, -d0
    return _ground_fit(pts, np.asarray(inliers, int), n, d0, up, np.asarray(axis_point, float).reshape(3))
