"""Initial alignment of the two sides from global features (paper: "Initial Alignment using Global Features").

The front and back reconstructions share no feature matches. Following the paper, eq. base is solved
in steps, each from a feature both sides see:

1. Canonical frame of each side: the ground plane (RANSAC with the lower-boundary rule of
   core.ground, normal near the cameras' up) gives Y (up); the first principal component of the
   cloud on the ground plane gives the row direction X; Z = X x Y is the depth direction, turned so
   that both sides' Z point the same way in the world (the front side's away from its cameras, the
   back side's towards them: the sides face each other). The ground is at Y = 0.
2. Orthographic front view (X, Y): the alpha-shape occlusion boundary of each side's points above
   the ground, and a rigid (+scale when a side is up to scale) Coherent Point Drift of the two
   boundaries (Myronenko and Song 2010) over the residual rotation about Z, the X and Y translation
   (and scale), started from X shifts on a grid: a side may start at the other end of the row, beyond
   CPD's reach. A row repeats itself every tree, so several starts are carried on (the best few of
   eq. dist, the shift at which trunks of like diameter line up) with CPD and without it, and the
   trunks decide (step 3).
3. Depth (Z) and heading: the paper aligns trunk surface points near the median trunk plane, which
   leaves an error up to a trunk's width. With trunk cylinders fitted per side the two sides see the
   same axis, so the trunk axes (at the diameter height), paired along the row, are fitted rigidly in
   the top view (X, Z). Of the starts, the one whose pairs agree best (axis gap and diameter
   difference) wins; if even that one disagrees, the sides are refused.

Result: the similarity odom_front <- odom_back, the trunk-to-trunk pairs and the overlap along the
row. Fewer than two trunks seen from both sides: `AlignmentError`, never a guessed merge.

Frames: each side's points, poses and trunks in its own odom frame; canonical frames as above;
metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import ndimage
from scipy.spatial import Delaunay, cKDTree

from orchard_mapping.core.geometry import make_transform
from orchard_mapping.core.ground import GroundParams, fit_local_ground
from orchard_mapping.errors import AlignmentError

__all__ = [
    "AlignmentParams",
    "AlignmentSide",
    "CanonicalFrame",
    "SideAlignment",
    "align_sides",
    "alpha_boundary",
    "canonical_frame",
    "cpd_rigid_2d",
    "icp_merge",
    "pair_trunks",
]


@dataclass
class AlignmentParams:
    """Settings of the initial alignment (config section `merge`)."""

    __pydantic_config__ = {"extra": "forbid"}

    voxel_m: float = 0.05  # m, the clouds are thinned to this grid first (density then weighs nothing)
    ground_max_tilt_deg: float = 30.0  # deg, the ground normal vs the cameras' mean up
    ground_clearance_m: float = 0.10  # m, front view: points lower than this are ground, left out
    depth_band_m: float = 1.5  # m, front view: points farther than this from the trunk plane (other rows) left out
    view_cell_m: float = 0.03  # m, front view thinned to this grid before the alpha shape
    alpha_m: float = 0.15  # m, the alpha-shape disc radius (occlusion boundary of the front view)
    boundary_points: int = 400  # the boundaries are thinned to at most this many points for CPD
    shift_step_m: float = 0.05  # m, X shifts tried before CPD
    cpd_outlier_weight: float = 0.3  # CPD's w: share of points without a partner (a side sees more of the row)
    cpd_iterations: int = 100
    trunk_height_m: float = 0.30  # m above the ground: where the trunk axes are compared
    pair_radius_m: float = 0.15  # m, trunk axes closer than this after alignment are one tree
    min_pairs: int = 2  # trunks seen from both sides needed for a merge
    shift_candidates: int = 4  # best shifts along the row carried through CPD and the top view
    # mm, median axis gap + median diameter difference of the paired trunks above which the pairs are taken
    # for different trees and the merge refused. The right shift scored 3.0 (9-tree partial_overlap), 5.7
    # (10-tree standard) and 9.8 mm (10-tree slope_weeds); shifts a tree or more off 21-110 mm.
    max_disagreement_mm: float = 16.0
    # pairs from which a smooth bend along the row (quadratic in X) is taken off the gaps before the check
    # above: a long row's own drift, not a sign of different trees (_bend_free_gaps)
    bend_min_pairs: int = 10
    # With fewer than min_pairs trunks seen from both sides: "global_features" (the paper's alignment without
    # pairs: the front views' CPD for the along-row shift, height and roll, each side's trunk line for depth and
    # heading; the result is flagged, its error is a trunk's width rather than millimetres) or "refuse".
    fallback: str = "global_features"


@dataclass(frozen=True)
class AlignmentSide:
    """What the alignment needs of one side, all in its odom frame."""

    points: np.ndarray  # (P, 3) m, fused cloud
    poses: np.ndarray  # (K, 4, 4) T_odom_cam of the keyframes (optical frame: z forward, y down)
    trunk_base: np.ndarray  # (T, 3) m, where each trunk axis meets its ground
    trunk_axis: np.ndarray  # (T, 3) unit, up
    trunk_ids: np.ndarray  # (T,) int, the trunk landmarks' ids
    scale_free: bool = False  # True for a colour-only side (up to scale)
    trunk_diameter: np.ndarray | None = None  # (T,) m, NaN where not measured (None: none measured)

    def __post_init__(self) -> None:
        if self.trunk_diameter is None:
            object.__setattr__(self, "trunk_diameter", np.full(len(self.trunk_ids), np.nan))


@dataclass(frozen=True)
class CanonicalFrame:
    T_canon_odom: np.ndarray  # (4, 4) rigid: rows of the rotation are X (row), Y (up), Z (depth)
    ground_inliers: int
    ground_rmse_m: float


@dataclass(frozen=True)
class SideAlignment:
    T_front_back: np.ndarray  # (4, 4) similarity odom_front <- odom_back: [s R | t]
    scale: float
    pairs: tuple[tuple[int, int], ...]  # (front trunk id, back trunk id)
    pair_gaps_m: tuple[float, ...]  # horizontal distance of each pair's axes at trunk_height_m after alignment
    overlap_m: tuple[float, float]  # X range of the row both sides cover, front canonical frame
    boundary_rms_m: float  # RMS of eq. dist between the aligned boundaries (inliers of CPD)
    front: CanonicalFrame
    back: CanonicalFrame
    log: list[str] = field(default_factory=list)
    # "trunk_pairs": the trunks seen from both sides set depth and heading; "trunk_lines": too few pairs, each
    # side's own trunk line did (AlignmentParams.fallback)
    method: str = "trunk_pairs"


BOUNDARY_INLIER_M = 0.10  # m, boundary points farther from the other side's are parts only one side sees
# m, trunk diameters closer than this vote fully for the shift that brings their trunks together: one side's
# diameter is 1-1.5 mm off the truth (MAE), trees of a row differ by centimetres
DIAMETER_VOTE_SIGMA_M = 0.003


# --------------------------------------------------------------------------- canonical frame

def _first_per_cell(points: np.ndarray, cell: float) -> np.ndarray:
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


def _voxel(points: np.ndarray, cell: float) -> np.ndarray:
    """(Q, 3) one point (the first) per occupied cell of a `cell` grid."""
    return points[_first_per_cell(points, cell)]


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
    thin = _voxel(pts, params.voxel_m)
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


# --------------------------------------------------------------------------- front-view occlusion boundary

def _alpha_boundary_indices(xy: np.ndarray, alpha: float) -> np.ndarray:
    """Sorted indices into xy (N >= 3, 2) of the vertices of edges that belong to exactly one Delaunay
    triangle whose circumradius is below alpha; none where the points are collinear."""
    try:
        tri = Delaunay(xy).simplices  # (T, 3)
    except Exception:  # scipy's QhullError: collinear or coincident points form no triangle
        return np.zeros(0, np.int64)
    a, b, c = xy[tri[:, 0]], xy[tri[:, 1]], xy[tri[:, 2]]
    la, lb, lc = (np.linalg.norm(b - c, axis=1), np.linalg.norm(c - a, axis=1), np.linalg.norm(a - b, axis=1))
    area2 = np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    radius = la * lb * lc / np.maximum(2.0 * area2, 1e-12)
    kept = tri[radius < alpha].astype(np.int64)
    if not len(kept):
        return np.zeros(0, np.int64)
    edges = np.sort(np.concatenate([kept[:, [0, 1]], kept[:, [1, 2]], kept[:, [2, 0]]]), axis=1)  # (3K, 2)
    key = np.sort(edges[:, 0] * len(xy) + edges[:, 1])  # one int64 per edge (np.unique over rows: 3x slower)
    once = np.ones(len(key), bool)
    same = key[1:] == key[:-1]
    once[1:] &= ~same
    once[:-1] &= ~same
    on = np.zeros(len(xy), bool)
    on[key[once] // len(xy)] = True
    on[key[once] % len(xy)] = True
    return np.flatnonzero(on)


def alpha_boundary(xy: np.ndarray, alpha: float, tile_points: int = 8000) -> np.ndarray:
    """(B, 2) points on the boundary of the 2D alpha shape of xy (N, 2): the vertices of edges that belong
    to exactly one Delaunay triangle whose circumradius is below alpha (in xy's order).

    The same points as one Delaunay triangulation of all of xy, computed locally, so that a long row costs
    what its length does (one triangulation of a 100-tree front view took 4.0 s, 4.1x a 30-tree one's;
    this 0.8 s). A boundary vertex touches an empty disc of radius alpha (a removed triangle's circumdisc,
    shrunk, or the outside of the hull), and every kept triangle at a point lies within 2 alpha of it:
      - an occupancy grid (cell alpha / 5) and two distance transforms find where such a disc can be
        (cells at least alpha - one cell diagonal from every occupied one); only points within alpha +
        a diagonal of those can be boundary vertices, only points within 2 alpha of those matter;
      - those are triangulated in tiles of about tile_points along x, each with 2.5 alpha of its
        neighbours around it, and each tile keeps the boundary vertices of its own stretch.
    """
    xy = np.asarray(xy, float)
    if len(xy) < 4:
        return xy.copy()
    cell = alpha / 5.0
    diag = cell * np.sqrt(2.0)
    pad = int(np.ceil(2.0 * alpha / cell)) + 2  # empty cells around: the outside of the hull is free
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(np.int64) + pad  # (N, 2)
    shape = ij.max(axis=0) + pad + 1
    if float(shape[0]) * float(shape[1]) > 5e7:  # a grid over 400 MB: triangulate all at once instead
        return xy[_alpha_boundary_indices(xy, alpha)]
    occupied = np.zeros(shape, bool)
    occupied[ij[:, 0], ij[:, 1]] = True
    eps = 1e-9
    free = ndimage.distance_transform_edt(~occupied) * cell >= alpha - diag - eps  # an empty disc's centre may be here
    to_free = (ndimage.distance_transform_edt(~free) * cell)[ij[:, 0], ij[:, 1]]  # (N,) m
    candidate = to_free <= alpha + diag + eps
    support = np.flatnonzero(to_free <= 3.0 * alpha + 2.0 * diag + eps)
    order = support[np.argsort(xy[support, 0], kind="stable")]
    x = xy[order, 0]
    n_tiles = max(1, len(order) // tile_points)
    cuts = np.quantile(x, np.linspace(0.0, 1.0, n_tiles + 1)) if len(x) else np.zeros(2)
    cuts[0], cuts[-1] = -np.inf, np.inf
    found = []
    for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
        a, b = np.searchsorted(x, [lo - 2.5 * alpha, hi + 2.5 * alpha])
        idx = order[a:b]
        if len(idx) < 3:
            continue
        on = idx[_alpha_boundary_indices(xy[idx], alpha)]
        found.append(on[(xy[on, 0] >= lo) & (xy[on, 0] < hi) & candidate[on]])
    return xy[np.sort(np.concatenate(found))] if found else np.zeros((0, 2))


VOXEL_CHUNK_POINTS = 300_000  # points per chunk of _voxel_centres


def _voxel_centres(points: np.ndarray, cell: float) -> np.ndarray:
    """(Q, 3) the centroid of each occupied cell of a `cell` grid: Open3D's voxel_down_sample, 2.2x
    faster than _voxel on the 30-tree row's 2.9 M points (0.35 vs 0.79 s).

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


def _front_view_boundary(points_c: np.ndarray, z_plane: float, params: AlignmentParams,
                         rng: np.random.Generator) -> np.ndarray:
    sel = (points_c[:, 1] > params.ground_clearance_m) & (np.abs(points_c[:, 2] - z_plane) < params.depth_band_m)
    xy = points_c[sel][:, :2]
    if len(xy) < 10:
        return np.zeros((0, 2))
    b = alpha_boundary(xy[_first_per_cell(xy, params.view_cell_m)], params.alpha_m)
    if len(b) > params.boundary_points:
        b = b[rng.choice(len(b), params.boundary_points, replace=False)]
    return b


# --------------------------------------------------------------------------- rigid CPD (2D)

def cpd_rigid_2d(fixed: np.ndarray, moving: np.ndarray, *, with_scale: bool, w: float = 0.3,
                 iterations: int = 100, tol: float = 1e-6) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Rigid Coherent Point Drift (Myronenko and Song 2010, Fig. 2): fixed X (N, 2) ~ s R moving + t.

    Returns (R (2, 2), t (2,), s, sigma2). Vectorised numpy: MEASURED 4x faster than pycpd on 2000
    points with the same result; probreg's rigid mode without scale mis-updates sigma2.
    """
    X, Y = np.asarray(fixed, float), np.asarray(moving, float)
    N, M, D = len(X), len(Y), 2
    R, t, s = np.eye(2), np.zeros(2), 1.0

    # Two (M, N) buffers reused by every iteration: fresh temporaries of this size cost page faults (one
    # iteration on 357 x 355 points took 6.0 ms with them, 1.8 ms in place, the same values).
    P, tmp = np.empty((M, N)), np.empty((M, N))

    def sq_dist(A: np.ndarray) -> np.ndarray:  # (M, N) squared distances from A (M, 2) to X, into P
        np.subtract(X[None, :, 0], A[:, None, 0], out=P)
        np.multiply(P, P, out=P)
        np.subtract(X[None, :, 1], A[:, None, 1], out=tmp)
        np.multiply(tmp, tmp, out=tmp)
        return np.add(P, tmp, out=P)

    sigma2 = float(np.sum(sq_dist(Y)) / (D * N * M))
    for _ in range(iterations):
        TY = s * Y @ R.T + t  # (M, 2)
        sq_dist(TY)  # P (M, N): squared distances
        np.divide(P, -2.0 * sigma2, out=P)
        # exp's underflow below e^-708 takes a slow path (2 vs 1.1 ms); what is cut off is < 1e-304
        np.maximum(P, -700.0, out=P)
        np.exp(P, out=P)
        c = (2 * np.pi * sigma2) ** (D / 2) * w / (1 - w) * M / N
        P /= np.maximum(P.sum(axis=0, keepdims=True) + c, 1e-300)
        Np = P.sum()
        if Np < 1e-9:
            break
        p_x, p_y = P.sum(axis=0), P.sum(axis=1)  # (N,), (M,)
        mu_x = X.T @ p_x / Np
        mu_y = Y.T @ p_y / Np
        Xh, Yh = X - mu_x, Y - mu_y
        A = Xh.T @ P.T @ Yh  # (2, 2)
        U, _, Vt = np.linalg.svd(A)
        C = np.diag([1.0, np.linalg.det(U @ Vt)])
        R = U @ C @ Vt
        trAR = float(np.trace(A.T @ R))
        yPy = float(np.sum(p_y * np.sum(Yh**2, axis=1)))
        if with_scale:
            s = trAR / yPy
        t = mu_x - s * R @ mu_y
        xPx = float(np.sum(p_x * np.sum(Xh**2, axis=1)))
        new = max((xPx - s * trAR) / (Np * D), 1e-10)
        if abs(sigma2 - new) < tol:
            sigma2 = new
            break
        sigma2 = new
    return R, t, s, sigma2


# --------------------------------------------------------------------------- trunks

def _trunk_points(side: AlignmentSide, T: np.ndarray, height: float) -> np.ndarray:
    """(T, 3) each trunk axis at `height` above the ground, in the frame T maps odom to (canonical)."""
    base = side.trunk_base @ T[:3, :3].T + T[:3, 3]
    axis = side.trunk_axis @ T[:3, :3].T
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    s = (height - base[:, 1]) / np.where(np.abs(axis[:, 1]) > 0.2, axis[:, 1], 1.0)
    return base + s[:, None] * axis


def _rigid_xz(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """(4, 4) rotation about Y and shift in X and Z taking src (N, 3) onto dst (N, 3) in the top view
    (2D Kabsch on the (X, Z) coordinates; N >= 2)."""
    a, b = src[:, [0, 2]], dst[:, [0, 2]]
    ma, mb = a.mean(axis=0), b.mean(axis=0)
    U, _, Vt = np.linalg.svd((b - mb).T @ (a - ma))
    R2 = U @ np.diag([1.0, np.linalg.det(U @ Vt)]) @ Vt
    t2 = mb - R2 @ ma
    G = np.eye(4)
    G[np.ix_([0, 2], [0, 2])] = R2
    G[[0, 2], 3] = t2
    return G


def _mutual_nearest(d: np.ndarray, radius: float) -> list[tuple[int, int, float]]:
    """(i, j, d_ij) for every i whose nearest j (in the distance matrix d (F, B)) has i as its nearest,
    closer than radius."""
    out = []
    for i in range(d.shape[0] if d.shape[1] else 0):
        j = int(np.argmin(d[i]))
        if d[i, j] < radius and int(np.argmin(d[:, j])) == i:
            out.append((i, j, float(d[i, j])))
    return out


def _pairs(pf: np.ndarray, pb: np.ndarray, radius: float) -> list[tuple[int, int, float]]:
    """Mutual nearest pairs of trunk points in the (X, Z) plane within radius: (i front, j back, gap)."""
    return _mutual_nearest(np.linalg.norm(pf[:, None, [0, 2]] - pb[None, :, [0, 2]], axis=2), radius)  # (F, B)


def _bend_free_gaps(pf: np.ndarray, pb: np.ndarray, params: AlignmentParams) -> np.ndarray:
    """Gaps (N,) m in the (X, Z) plane between paired trunk points pf, pb (N, 3), less what a smooth bend
    along the row explains: with bend_min_pairs pairs or more, the offsets' quadratic in X is taken off.
    Each side's own drift bends a long row: on a 30-tree row the right shift's pairs were 19.8 mm apart
    (median) after the one rigid fit, over max_disagreement_mm, and the merge was refused. A pair one tree
    off keeps its offset (the trees' spacing and diameters differ from tree to tree), which no smooth
    bend explains."""
    off = (pb - pf)[:, [0, 2]]  # (N, 2)
    if len(off) < params.bend_min_pairs:
        return np.linalg.norm(off, axis=1)
    x = pf[:, 0]
    u = (x - x.mean()) / max(float(np.ptp(x)), 1e-6)
    A = np.stack([np.ones_like(u), u, u * u], axis=1)  # (N, 3)
    coef, *_ = np.linalg.lstsq(A, off, rcond=None)  # (3, 2)
    return np.linalg.norm(off - A @ coef, axis=1)


def _shift_costs(Bf: np.ndarray, Bb: np.ndarray, params: AlignmentParams) -> tuple[np.ndarray, np.ndarray]:
    """(shifts (S,), cost (S,)): eq. dist between the front-view boundaries over the stretch both cover
    at each shift along the row (truncated at 0.3 m per point); shifts leaving less than a third of the
    shorter side in common cost infinity. Counting the common stretch only, a shift is not preferred
    for overlapping more (the sides may cover different stretches of the row).

    All shifts at once from the point pairs closer than the truncation at some shift (a pair is that
    close over a dozen shifts at most): a loop of nearest-neighbour queries per shift took 1.4 s on a
    100-tree row (3851 shifts), 0.4 s on 30."""
    cut = 0.3  # m, truncation of eq. dist
    xf, yf, xb, yb = Bf[:, 0], Bf[:, 1], Bb[:, 0], Bb[:, 1]
    lo, hi = xf.min() - xb.max(), xf.max() - xb.min()
    shifts = np.arange(lo, hi + params.shift_step_m, params.shift_step_m)  # (S,)
    S = len(shifts)
    span = min(np.ptp(xf), np.ptp(xb))
    x0 = np.maximum(xf.min(), xb.min() + shifts)  # (S,) the common stretch at each shift
    x1 = np.minimum(xf.max(), xb.max() + shifts)
    in_f = (xf[None] >= x0[:, None]) & (xf[None] <= x1[:, None])  # (S, F)
    in_b = (xb[None] + shifts[:, None] >= x0[:, None]) & (xb[None] + shifts[:, None] <= x1[:, None])  # (S, B)
    # Pairs (i front, j back) within the cut in height, and the shifts k that bring them within it.
    i, j = np.nonzero(np.abs(yf[:, None] - yb[None]) < cut)
    dx, dy = xf[i] - xb[j], yf[i] - yb[j]
    reach = np.sqrt(cut * cut - dy * dy)  # |dx - shift| below this: closer than the cut
    k_lo = np.clip(np.ceil((dx - reach - lo) / params.shift_step_m).astype(np.int64), 0, S)
    k_hi = np.clip(np.floor((dx + reach - lo) / params.shift_step_m).astype(np.int64) + 1, 0, S)
    n_k = np.maximum(k_hi - k_lo, 0)
    e = np.repeat(np.arange(len(i)), n_k)  # (E,) pair of each (pair, shift) entry
    k = np.repeat(k_lo, n_k) + (np.arange(len(e)) - np.repeat(np.cumsum(n_k) - n_k, n_k))
    ie, je = i[e], j[e]
    d = np.hypot(xf[ie] - (xb[je] + shifts[k]), yf[ie] - yb[je])  # (E,) m
    d1 = np.full((S, len(xb)), cut)  # back point -> nearest front boundary point (all of it)
    np.minimum.at(d1, (k, je), d)
    d2 = np.full((S, len(xf)), cut)  # front point -> nearest back boundary point on the common stretch
    both = in_b[k, je]
    np.minimum.at(d2, (k[both], ie[both]), d[both])
    d1 = np.minimum(d1, cut)
    d2 = np.minimum(d2, cut)
    n_f, n_b = in_f.sum(axis=1), in_b.sum(axis=1)
    ok = (x1 - x0 >= span / 3) & (n_f >= 10) & (n_b >= 10)
    with np.errstate(invalid="ignore", divide="ignore"):
        cost = np.sum(d1 * d1 * in_b, axis=1) / n_b + np.sum(d2 * d2 * in_f, axis=1) / n_f
    return shifts, np.where(ok, cost, np.inf)


def _trunk_vote_shift(tf: np.ndarray, tb: np.ndarray, front: AlignmentSide, back: AlignmentSide,
                      params: AlignmentParams) -> float | None:
    """The X shift along the row (m) at which the most trunks of like diameter line up, or None without
    diameters on both sides: each front and back trunk pair votes for the shift that brings them together,
    weighted by how alike their diameters are (Gaussian, DIAMETER_VOTE_SIGMA_M), smoothed over the pair
    radius. A shift candidate independent of the front views: on a row whose stretches look alike (a row
    tiled from one 10-tree stretch) every shift by a stretch fits the front views as well as the right one,
    and the best few of them may leave the right one out (100 tiled trees: paired 40 trees 57 m off)."""
    df, db = front.trunk_diameter, back.trunk_diameter
    if len(tf) == 0 or len(tb) == 0 or not (np.isfinite(df).any() and np.isfinite(db).any()):
        return None
    w = np.exp(-0.5 * ((df[:, None] - db[None]) / DIAMETER_VOTE_SIGMA_M) ** 2)  # (F, B), NaN where unmeasured
    w = np.where(np.isfinite(w), w, 0.0)
    if w.max() < 0.5:
        return None
    dx = tf[:, None, 0] - tb[None, :, 0]  # (F, B) the shift each pair votes for
    step = params.shift_step_m
    edges = np.arange(dx.min() - step / 2, dx.max() + step, step)
    hist, _ = np.histogram(dx.ravel(), bins=edges, weights=w.ravel())
    votes = ndimage.gaussian_filter1d(hist, params.pair_radius_m / step, mode="constant")
    k = int(np.argmax(votes))
    return float(0.5 * (edges[k] + edges[k + 1]))


def _local_minima(x: np.ndarray, y: np.ndarray, k: int, separation: float) -> list[float]:
    """Up to k positions of the lowest finite local minima of y(x), at least `separation` apart."""
    order = [i for i in np.argsort(y) if np.isfinite(y[i])]
    out: list[float] = []
    for i in order:
        if all(abs(x[i] - o) >= separation for o in out):
            out.append(float(x[i]))
        if len(out) == k:
            break
    return out


@dataclass(frozen=True)
class _Candidate:
    S: np.ndarray  # (4, 4) front canonical <- back canonical
    pairs: list[tuple[int, int, float]]
    scale: float
    boundary_rms_m: float
    tb_al: np.ndarray  # (T_b, 3) back trunk points moved by S
    score_mm: float  # median gap of the paired axes + median diameter difference (lower is better)
    log: list[str]
    cpd: bool = True  # the front views were fitted by CPD (else the start shift was kept)


def _front_view_fit(dx0: float, Bf: np.ndarray, Bb: np.ndarray, scale_free: bool, params: AlignmentParams,
                    use_cpd: bool = True) -> tuple[np.ndarray, float, float, str, tuple[float, float]]:
    """CPD of the front-view boundaries Bf, Bb (N, 2) from shift dx0 along the row (use_cpd False: the shift as
    it is): (S (4, 4) front canonical <- back canonical, rotation about Z and X, Y shift only; scale; boundary
    RMS m; a log line; the X range both cover at dx0)."""
    # CPD on the stretch both cover at this shift: given all of both boundaries it slides towards the
    # largest overlap, whatever the shift it started from (partial_overlap row: every start ended 1.85 m off).
    b0 = Bb + [dx0, 0.0]
    x0, x1 = max(Bf[:, 0].min(), b0[:, 0].min()), min(Bf[:, 0].max(), b0[:, 0].max())
    fin = Bf[(Bf[:, 0] >= x0) & (Bf[:, 0] <= x1)]
    bin_ = b0[(b0[:, 0] >= x0) & (b0[:, 0] <= x1)]
    if len(fin) < 10 or len(bin_) < 10:
        raise AlignmentError(f"the front views share too little at a shift of {dx0:+.2f} m along the row")
    if use_cpd:
        R2, t2, s, sigma2 = cpd_rigid_2d(fin, bin_, with_scale=scale_free, w=params.cpd_outlier_weight,
                                         iterations=params.cpd_iterations)
    else:
        R2, t2, s, sigma2 = np.eye(2), np.zeros(2), 1.0, float("nan")
    t2 = t2 + s * R2 @ np.array([dx0, 0.0])
    # Lift the 2D similarity in (X, Y) to 3D: rotation about Z.
    R3 = np.eye(3)
    R3[:2, :2] = R2
    S = make_transform(R3, np.array([t2[0], t2[1], 0.0]), s)  # front canonical <- back canonical (no Z yet)
    Bb_al = s * Bb @ R2.T + t2
    d, _ = cKDTree(Bf).query(Bb_al)
    inl = d < BOUNDARY_INLIER_M
    b_rms = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else float("nan")
    line = (("" if use_cpd else "no CPD (the start shift as it is): ") +
            f"CPD: rotation about Z {np.degrees(np.arctan2(R2[1, 0], R2[0, 0])):+.2f} deg, "
            f"t ({t2[0]:+.3f}, {t2[1]:+.3f}) m, scale {s:.4f}, sigma {1000 * np.sqrt(sigma2):.1f} mm, "
            f"boundary RMS {1000 * b_rms:.1f} mm over {inl.mean():.0%} of the back boundary")
    return S, float(s), b_rms, line, (float(x0), float(x1))


def _from_shift(dx0: float, Bf: np.ndarray, Bb: np.ndarray, tf: np.ndarray, tb: np.ndarray, front: AlignmentSide,
                back: AlignmentSide, scale_free: bool, params: AlignmentParams, use_cpd: bool = True) -> _Candidate:
    """CPD of the front views from shift dx0 (or, use_cpd False, the shift as it is), then the top view from
    the trunks paired along the row."""
    S, s, b_rms, cpd_log, _ = _front_view_fit(dx0, Bf, Bb, scale_free, params, use_cpd)
    log = [cpd_log]
    # Top view (X, Z): trunks paired along the row, then the rigid 2D fit of their axes (rotation about
    # Y, X and Z shift): the depth offset, and the yaw the front views cannot see.
    tb_al = tb @ S[:3, :3].T + S[:3, 3]
    near = _pairs(tf * [1, 1, 0], tb_al * [1, 1, 0], 3 * params.pair_radius_m)  # X only: Z still unknown
    if len(near) < params.min_pairs:
        raise AlignmentError(
            f"only {len(near)} trunk(s) seen from both sides (front {len(tf)}, back {len(tb)} trunks): "
            f"at least {params.min_pairs} are needed to merge the sides")
    i_f, i_b = [i for i, _, _ in near], [j for _, j, _ in near]
    keep = np.ones(len(near), bool)
    for _ in range(2):  # refit without pairs far off the first fit (a trunk paired with its neighbour's)
        G = _rigid_xz(tb_al[np.array(i_b)[keep]], tf[np.array(i_f)[keep]])
        moved = tb_al[i_b] @ G[:3, :3].T + G[:3, 3]
        gap = np.linalg.norm((moved - tf[i_f])[:, [0, 2]], axis=1)
        keep = gap <= max(3 * np.median(gap), params.pair_radius_m / 3)
        if keep.sum() < params.min_pairs:
            keep[np.argsort(gap)[:params.min_pairs]] = True
    S = G @ S
    tb_al = tb @ S[:3, :3].T + S[:3, 3]
    pairs = _pairs(tf, tb_al, params.pair_radius_m)
    log.append(f"top view from {int(keep.sum())} of {len(near)} trunks paired along the row: rotation about Y "
               f"{np.degrees(np.arctan2(G[0, 2], G[0, 0])):+.2f} deg, depth offset {G[2, 3]:+.3f} m; "
               f"{len(pairs)} pairs within {params.pair_radius_m:g} m")
    if len(pairs) < params.min_pairs:
        raise AlignmentError(
            f"only {len(pairs)} trunk pair(s) agree after alignment (of {len(near)} matched along the row): "
            f"at least {params.min_pairs} are needed to merge the sides")
    gaps_mm = 1000 * _bend_free_gaps(tf[[i for i, _, _ in pairs]], tb_al[[j for _, j, _ in pairs]], params)
    dd = [abs(front.trunk_diameter[i] - back.trunk_diameter[j]) * 1000 for i, j, _ in pairs
          if np.isfinite(front.trunk_diameter[i]) and np.isfinite(back.trunk_diameter[j])]
    score = float(np.median(gaps_mm)) + (float(np.median(dd)) if dd else 0.0)
    return _Candidate(S, pairs, float(s), b_rms, tb_al, score, log, use_cpd)


# --------------------------------------------------------------------------- the whole step

def align_sides(front: AlignmentSide, back: AlignmentSide, params: AlignmentParams,
                rng: np.random.Generator) -> SideAlignment:
    """Initial similarity odom_front <- odom_back and trunk pairs (module docstring)."""
    log: list[str] = []
    # Every step below works on a grid no finer than the front view's cells: thinning the clouds to it
    # once makes the alignment's cost follow the row's area, not its point count (30-tree row: the
    # full clouds' transforms and cell sorts took 15 of 17 s).
    thin_f = _voxel_centres(front.points, params.view_cell_m)  # (Q, 3) odom_front
    thin_b = _voxel_centres(back.points, params.view_cell_m)
    cf = canonical_frame(thin_f, front.poses, "front", params, rng)
    cb = canonical_frame(thin_b, back.poses, "back", params, rng)
    Pf = thin_f @ cf.T_canon_odom[:3, :3].T + cf.T_canon_odom[:3, 3]
    Pb = thin_b @ cb.T_canon_odom[:3, :3].T + cb.T_canon_odom[:3, 3]
    tf = _trunk_points(front, cf.T_canon_odom, params.trunk_height_m)
    tb = _trunk_points(back, cb.T_canon_odom, params.trunk_height_m)
    zf = float(np.median(tf[:, 2])) if len(tf) else float(np.median(Pf[:, 2]))
    zb = float(np.median(tb[:, 2])) if len(tb) else float(np.median(Pb[:, 2]))
    Bf = _front_view_boundary(Pf, zf, params, rng)
    Bb = _front_view_boundary(Pb, zb, params, rng)
    if len(Bf) < 20 or len(Bb) < 20:
        raise AlignmentError(f"too little above the ground to align the sides' front views "
                             f"({len(Bf)} front, {len(Bb)} back boundary points)")
    # X shift: a row repeats itself every tree, so the front views alone may fit best one tree off (a
    # 9-tree partial_overlap row: 1.85 m off, silently). The best few shifts of eq. dist are each carried
    # through CPD and the top view; the one whose paired trunks agree best (gap of their axes, and their
    # diameters, which differ from tree to tree by centimetres) wins.
    shifts, cost = _shift_costs(Bf, Bb, params)
    scale_free = front.scale_free or back.scale_free
    tried: list[tuple[float, float, _Candidate]] = []
    failures = []
    starts = _local_minima(shifts, cost, params.shift_candidates, params.pair_radius_m * 4)
    voted = _trunk_vote_shift(tf, tb, front, back, params)
    if voted is not None and all(abs(voted - d) >= params.pair_radius_m * 4 for d in starts):
        starts.append(voted)
    # Each start is also carried through without CPD (not for a side up to scale: CPD finds the scale): CPD
    # may slide off a right start (a row whose stretches repeat: started 0.7 m from the truth, it ended half a
    # tree off, its sigma collapsed on 8 % of the boundary); the trunks' agreement then picks the start.
    for dx0 in starts:
        for use_cpd in (True, False) if not scale_free else (True,):
            try:
                cand = _from_shift(dx0, Bf, Bb, tf, tb, front, back, scale_free, params, use_cpd)
            except AlignmentError as err:
                failures.append(str(err))
                continue
            tried.append((cand.score_mm, dx0, cand))
    if not tried:
        reason = failures[0] if failures else "no shift along the row aligns the sides' front views"
        if params.fallback != "global_features" or not starts:
            raise AlignmentError(reason)
        return _align_by_trunk_lines(starts[0], Bf, Bb, tf, tb, front, back, cf, cb, scale_free, params, reason)
    tried.sort(key=lambda x: x[0])
    _, dx0, best = tried[0]
    if best.score_mm > params.max_disagreement_mm:
        reason = (f"the trunks the sides seem to share do not agree (best shift {dx0:+.2f} m along the row: median "
                  f"axis gap + diameter difference {best.score_mm:.1f} mm > {params.max_disagreement_mm:g} mm): "
                  "they are probably different trees (the sides cover different stretches of the row, or both "
                  "recordings are of the same side)")
        if params.fallback != "global_features":
            raise AlignmentError(reason)
        return _align_by_trunk_lines(starts[0], Bf, Bb, tf, tb, front, back, cf, cb, scale_free, params, reason)
    log.append(f"front-view X shift {dx0:+.2f} m, the best of {len(tried)} candidate(s) by trunk agreement "
               + ", ".join(f"{d:+.2f} m{'' if c.cpd else ' (no CPD)'}: {sc:.1f} mm" for sc, d, c in tried[:4]))
    log += best.log
    S, pairs, s, b_rms, tb_al = best.S, best.pairs, best.scale, best.boundary_rms_m, best.tb_al
    T = np.linalg.inv(cf.T_canon_odom) @ S @ cb.T_canon_odom
    xs_f, xs_b = tf[:, 0], tb_al[:, 0]
    overlap = (float(max(xs_f.min(), xs_b.min())), float(min(xs_f.max(), xs_b.max())))
    return SideAlignment(
        T_front_back=T, scale=float(s),
        pairs=tuple((int(front.trunk_ids[i]), int(back.trunk_ids[j])) for i, j, _ in pairs),
        pair_gaps_m=tuple(g for _, _, g in pairs), overlap_m=overlap, boundary_rms_m=b_rms,
        front=cf, back=cb, log=log)


def _trunk_line(t: np.ndarray) -> tuple[float, float] | None:
    """(depth Z at X = 0, dZ/dX) of the line through trunk points t (T, 3) in the top view (X, Z), a robust
    fit (the median of the pairwise slopes, Theil-Sen); slope 0 from a single trunk; None without trunks."""
    if len(t) == 0:
        return None
    if len(t) == 1:
        return float(t[0, 2]), 0.0
    i, j = np.triu_indices(len(t), 1)
    dx = t[j, 0] - t[i, 0]
    ok = np.abs(dx) > 0.3  # m: trunks of neighbouring trees, not one trunk found twice
    slope = float(np.median((t[j, 2] - t[i, 2])[ok] / dx[ok])) if ok.any() else 0.0
    return float(np.median(t[:, 2] - slope * t[:, 0])), slope


# trunks each side needs before their mean axis sets the tilt, and their line the heading, between the sides
# (trunk_lines fallback; with fewer, the canonical frames' ground and row direction stand): trees lean and stand
# off the row line by centimetres each
TILT_MIN_TRUNKS = 4


def _path_heading(c: np.ndarray) -> float | None:
    """rad: the direction in the top view (X, Z) of a camera path c (K, 3) (canonical frame), the angle of its
    first principal axis from X, in (-pi/2, pi/2]; None for a path shorter than 0.5 m or not straight."""
    xz = c[:, [0, 2]] - c[:, [0, 2]].mean(axis=0)
    if len(xz) < 3:
        return None
    _, sv, Vt = np.linalg.svd(xz, full_matrices=False)
    if np.ptp(xz @ Vt[0]) < 0.5 or sv[1] > 0.2 * sv[0]:
        return None
    return float((np.arctan2(Vt[0, 1], Vt[0, 0]) + np.pi / 2) % np.pi - np.pi / 2)


def _mean_axis(axes: np.ndarray) -> np.ndarray:
    """(3,) unit: the mean of unit axes (T, 3) pointing up (+Y of a canonical frame)."""
    a = np.sum(axes * np.sign(axes[:, 1:2] + 1e-12), axis=0)
    return a / np.linalg.norm(a)


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking unit a (3,) onto unit b (3,) (Rodrigues)."""
    v, c = np.cross(a, b), float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def _align_by_trunk_lines(dx0: float, Bf: np.ndarray, Bb: np.ndarray, tf: np.ndarray, tb: np.ndarray,
                          front: AlignmentSide, back: AlignmentSide, cf: CanonicalFrame, cb: CanonicalFrame,
                          scale_free: bool, params: AlignmentParams, reason: str) -> SideAlignment:
    """The alignment without trunk pairs (paper, "Alignment in Depth Direction using Trunk Information": the
    median trunk planes): the front views' CPD from the best shift dx0 sets the along-row shift, height and roll;
    each side's own trunks, seen from it alone, lie on the row's trunk line, and bringing the two lines
    together in the top view sets the depth and, with two trunks or more on each side, the heading. The error
    left is up to a trunk's width across the row; along the row the front views' (a tree's spacing where the
    row repeats itself). The trunk pairs there are (fewer than min_pairs) set the along-row shift."""
    lf, lb0 = _trunk_line(tf), _trunk_line(tb)
    if lf is None or lb0 is None:
        raise AlignmentError(f"{reason}; and no trunk line to align the depth on (front {len(tf)}, back "
                             f"{len(tb)} trunks)")
    try:
        S, s, b_rms, cpd_log, (x0, x1) = _front_view_fit(dx0, Bf, Bb, scale_free, params)
    except AlignmentError as err:
        raise AlignmentError(f"{reason}; and without trunk pairs: {err}") from err
    log = [f"fallback (alignment.fallback = global_features): {reason}", cpd_log]
    # Tilt: the whole sides' ground planes differ by degrees (each side sees mostly its own strip), the trunks
    # stand the same in both: the back trunks' mean axis is turned onto the front trunks' (about their centre).
    # The trees both sides saw (paired along the row: X only, the depth is not known yet) are the same trunks;
    # else, with TILT_MIN_TRUNKS a side, their leans average out.
    axes_f = front.trunk_axis @ cf.T_canon_odom[:3, :3].T
    axes_b = back.trunk_axis @ cb.T_canon_odom[:3, :3].T @ S[:3, :3].T
    tb_al = tb @ S[:3, :3].T + S[:3, 3]
    along = _pairs(tf * [1, 1, 0], tb_al * [1, 1, 0], 3 * params.pair_radius_m)
    many = min(len(tf), len(tb)) >= TILT_MIN_TRUNKS
    Rt = np.eye(3)
    if along:
        Rt = _rotation_between(_mean_axis(axes_b[[j for _, j, _ in along]]), _mean_axis(axes_f[[i for i, _, _ in along]]))
    elif many:
        Rt = _rotation_between(_mean_axis(axes_b), _mean_axis(axes_f))
    c_b = tb_al.mean(axis=0)
    S = make_transform(Rt, c_b - Rt @ c_b) @ S
    tb_al = tb @ S[:3, :3].T + S[:3, 3]
    lb = _trunk_line(tb_al)
    assert lb is not None
    c_b = tb_al.mean(axis=0)
    # Heading: the two trunk lines' slopes agree (with TILT_MIN_TRUNKS a side); else the two camera paths, which
    # run along the row, are made parallel (the canonical frames' row direction, a principal direction of each
    # cloud, is off by 26 deg on a 1-tree row 1.3 m long, where the hedge behind is as long as the row).
    if many:
        yaw = float(np.arctan(lf[1]) - np.arctan(lb[1]))
    else:
        hf = _path_heading(front.poses[:, :3, 3] @ cf.T_canon_odom[:3, :3].T)
        hb = _path_heading(back.poses[:, :3, 3] @ cb.T_canon_odom[:3, :3].T @ S[:3, :3].T)
        yaw = 0.0 if hf is None or hb is None else float((hf - hb + np.pi / 2) % np.pi - np.pi / 2)
    xm = 0.5 * (x0 + x1)  # the common stretch's middle: where the two lines are brought together
    c, sn = np.cos(yaw), np.sin(yaw)
    Ry = np.eye(3)
    Ry[np.ix_([0, 2], [0, 2])] = [[c, -sn], [sn, c]]  # rotation about Y taking the back heading onto the front
    G = make_transform(Ry, c_b - Ry @ c_b)  # about the back trunks' centre: their place along the row stays
    S = G @ S
    tb_al = tb @ S[:3, :3].T + S[:3, 3]
    lb = _trunk_line(tb_al)
    assert lb is not None
    G = np.eye(4)
    G[2, 3] = (lf[0] + lf[1] * xm) - (lb[0] + lb[1] * xm)  # the back line onto the front one there
    S = G @ S
    tb_al = tb @ S[:3, :3].T + S[:3, 3]
    near = _pairs(tf, tb_al, 3 * params.pair_radius_m)
    if near:  # trees seen from both sides (fewer than min_pairs): their trunks set the shift along the row, and
        # their feet (each on its side's ground under the tree) the height, which the front views set to a few cm
        S[0, 3] += float(np.median([tf[i, 0] - tb_al[j, 0] for i, j, _ in near]))
        foot_f = front.trunk_base @ cf.T_canon_odom[:3, :3].T + cf.T_canon_odom[:3, 3]
        foot_b = (back.trunk_base @ cb.T_canon_odom[:3, :3].T + cb.T_canon_odom[:3, 3]) @ S[:3, :3].T + S[:3, 3]
        S[1, 3] += float(np.median([foot_f[i, 1] - foot_b[j, 1] for i, j, _ in near]))
        tb_al = tb @ S[:3, :3].T + S[:3, 3]
    pairs = _pairs(tf, tb_al, params.pair_radius_m)
    log.append(f"front views from shift {dx0:+.2f} m; trunk lines "
               f"(front {len(tf)}, back {len(tb)} trunks): heading {np.degrees(yaw):+.2f} deg, then a depth offset "
               f"{G[2, 3]:+.3f} m; {len(pairs)} trunk pair(s) within {params.pair_radius_m:g} m after it")
    T = np.linalg.inv(cf.T_canon_odom) @ S @ cb.T_canon_odom
    overlap = (float(x0), float(x1))
    return SideAlignment(
        T_front_back=T, scale=float(s),
        pairs=tuple((int(front.trunk_ids[i]), int(back.trunk_ids[j])) for i, j, _ in pairs),
        pair_gaps_m=tuple(g for _, _, g in pairs), overlap_m=overlap, boundary_rms_m=b_rms,
        front=cf, back=cb, log=log, method="trunk_lines")


# --------------------------------------------------------------------------- baseline

def icp_merge(front: AlignmentSide, back: AlignmentSide, params: AlignmentParams, rng: np.random.Generator,
              max_distance_m: float = 0.30) -> np.ndarray:
    """The ICP baseline: point-to-plane ICP (Open3D) of the thinned clouds, started from the sides'
    canonical frames (ground and PCA: the sides facing each other) with the clouds' medians brought
    together. Returns T_front_back (4, 4). The paper reports that ICP fails here: the two
    sides see different surfaces of every tree."""
    import open3d as o3d

    # Each cloud thinned once to the canonical frame's grid (which then keeps every point of it).
    thin_f = _voxel(np.asarray(front.points, float), params.voxel_m)  # (Q, 3) odom_front
    thin_b = _voxel(np.asarray(back.points, float), params.voxel_m)
    cf = canonical_frame(thin_f, front.poses, "front", params, rng)
    cb = canonical_frame(thin_b, back.poses, "back", params, rng)
    # Generous to ICP: the clouds' medians above the ground brought together along the row and in depth.
    med = []
    for thin, c in ((thin_f, cf), (thin_b, cb)):
        P = thin @ c.T_canon_odom[:3, :3].T + c.T_canon_odom[:3, 3]
        med.append(np.median(P[P[:, 1] > params.ground_clearance_m], axis=0))
    shift = np.eye(4)
    shift[[0, 2], 3] = (med[0] - med[1])[[0, 2]]
    T0 = np.linalg.inv(cf.T_canon_odom) @ shift @ cb.T_canon_odom

    def cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=3 * params.voxel_m, max_nn=30))
        return pc

    res = o3d.pipelines.registration.registration_icp(
        cloud(thin_b), cloud(thin_f), max_distance_m, T0,
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=100))
    return np.asarray(res.transformation)


def pair_trunks(front: AlignmentSide, back: AlignmentSide, T_front_back: np.ndarray,
                radius_m: float) -> tuple[tuple[int, int], ...]:
    """Trunk pairs (front id, back id) whose axes, at the trunk bases, are mutual nearest within radius_m
    once the back side is moved by T_front_back (horizontal distance in the front frame, up = mean axis)."""
    if not len(front.trunk_base) or not len(back.trunk_base):
        return ()
    up = front.trunk_axis.mean(axis=0)
    up /= np.linalg.norm(up)
    bb = back.trunk_base @ T_front_back[:3, :3].T + T_front_back[:3, 3]
    d = front.trunk_base[:, None, :] - bb[None]  # (F, B, 3)
    d = np.linalg.norm(d - (d @ up)[..., None] * up, axis=2)
    return tuple((int(front.trunk_ids[i]), int(back.trunk_ids[j])) for i, j, _ in _mutual_nearest(d, radius_m))

