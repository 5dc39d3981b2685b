"""Canopy geometry of one segmented tree (paper: "Canopy Volume", "Tree Height").

- `alpha_complex` / `alpha_complex_volume`: the alpha complex of a point set is the union of the Delaunay
  tetrahedra whose circumradius is below alpha (Edelsbrunner & Muecke 1994). Its volume is the paper's
  alpha-shape canopy volume, and the simulator's ground truth uses this same function (one definition).
  Open3D's alpha-shape meshes are not watertight, so the volume is summed over the tetrahedra instead.
- `alpha_regions`: connected regions of the complex (tetrahedra sharing a face).
- `tree_height`: from the tree's local ground plane to the highest point that has neighbours around it
  (a depth camera leaves isolated flying points above canopies; a raw maximum takes them).
- `canopy_volume`: the alpha-complex volume of the tree's points above its clear trunk.
- `voxel_downsample`: one point per occupied voxel (the centroid), with the map back to the input points.

Frames: every point and vector is in the map frame, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, cKDTree

from orchard_mapping.core.geometry import checked_unit
from orchard_mapping.errors import OrchardMappingError

__all__ = [
    "AlphaComplex",
    "CanopyError",
    "alpha_complex",
    "alpha_complex_volume",
    "alpha_regions",
    "canopy_base_height",
    "canopy_volume",
    "height_above_plane",
    "main_body",
    "tree_height",
    "voxel_downsample",
]

# Coordinates are rounded to 1 um before the Delaunay: duplicate points (a fused cloud has them) make qhull
# build flat tetrahedra; 1 um is far below any sensor's resolution.
_ROUND_DECIMALS = 6
# m^3: tetrahedra with less volume are flat (their circumcentre is ill-defined): never kept.
_FLAT_TET_M3 = 1e-12


class CanopyError(OrchardMappingError, ValueError):
    """A canopy measurement got unusable input (wrong shapes, a zero normal, a non-positive alpha)."""


@dataclass(frozen=True)
class AlphaComplex:
    """The tetrahedra of a Delaunay tetrahedralisation with circumradius below alpha."""

    points: np.ndarray  # (P, 3) m, the de-duplicated input points the tetrahedra index
    tetrahedra: np.ndarray  # (K, 4) int, vertex indices into `points`, the kept tetrahedra only
    volumes: np.ndarray  # (K,) m^3, volume of each kept tetrahedron
    alpha_m: float  # m, the circumradius bound

    @property
    def volume_m3(self) -> float:
        return float(np.sum(self.volumes))


def _check_points(points: np.ndarray, what: str) -> np.ndarray:
    pts = np.asarray(points, float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise CanopyError(f"{what} must be (N, 3), got shape {pts.shape}")
    return pts


def alpha_complex(points: np.ndarray, alpha_m: float) -> AlphaComplex:
    """The alpha complex of points (N, 3): Delaunay tetrahedra with circumradius < alpha_m (m)."""
    pts = _check_points(points, "alpha complex points")
    if not alpha_m > 0:
        raise CanopyError(f"alpha must be > 0 m, got {alpha_m!r}")
    pts = np.unique(np.round(pts, _ROUND_DECIMALS), axis=0)  # (P, 3)
    empty = AlphaComplex(pts, np.zeros((0, 4), np.int64), np.zeros(0), float(alpha_m))
    if len(pts) < 4:
        return empty
    try:
        tet = Delaunay(pts).simplices  # (T, 4)
    except Exception:  # qhull: all points coplanar or collinear, so no tetrahedron has volume
        return empty
    a = pts[tet[:, 0]]
    m = np.stack([pts[tet[:, 1]] - a, pts[tet[:, 2]] - a, pts[tet[:, 3]] - a], axis=1)  # (T, 3, 3) edges
    det = np.linalg.det(m)
    vol = np.abs(det) / 6.0  # (T,)
    ok = vol > _FLAT_TET_M3
    # Circumcentre c (relative to vertex a) solves 2 e_i . c = |e_i|^2 for the three edges e_i.
    rhs = 0.5 * np.sum(m[ok] ** 2, axis=2)  # (T_ok, 3)
    centre = np.linalg.solve(m[ok], rhs[..., None])[..., 0]  # (T_ok, 3)
    radius = np.full(len(tet), np.inf)
    radius[ok] = np.linalg.norm(centre, axis=1)
    keep = radius < alpha_m
    return AlphaComplex(pts, tet[keep], vol[keep], float(alpha_m))


def alpha_complex_volume(points: np.ndarray, alpha_m: float) -> float:
    """Volume (m^3) of the alpha complex of points (N, 3) in m: the sum of the volumes of the Delaunay
    tetrahedra with circumradius < alpha_m. 0 with fewer than 4 distinct points."""
    return alpha_complex(points, alpha_m).volume_m3


def alpha_regions(cx: AlphaComplex) -> tuple[int, np.ndarray]:
    """Connected regions of an alpha complex: (number of regions, region of each kept tetrahedron (K,)).
    Two tetrahedra are connected when they share a face (three vertices)."""
    k = len(cx.tetrahedra)
    if k == 0:
        return 0, np.zeros(0, np.int64)
    faces = np.concatenate([np.delete(cx.tetrahedra, j, axis=1) for j in range(4)])  # (4K, 3)
    owner = np.tile(np.arange(k), 4)  # (4K,)
    faces = np.sort(faces, axis=1)
    order = np.lexsort(faces.T[::-1])
    f, o = faces[order], owner[order]
    same = np.all(f[1:] == f[:-1], axis=1)  # (4K-1,) a face shared by two tetrahedra
    g = coo_matrix((np.ones(int(same.sum())), (o[:-1][same], o[1:][same])), shape=(k, k))
    return connected_components(g, directed=False)


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    return checked_unit(v, what, CanopyError)


def height_above_plane(points: np.ndarray, ground_point: np.ndarray, ground_normal: np.ndarray) -> np.ndarray:
    """Signed height (N,) m of points (N, 3) above the plane through ground_point (3,) with up normal (3,)."""
    n = _unit(ground_normal, "ground normal")
    return (_check_points(points, "points") - np.asarray(ground_point, float).reshape(3)) @ n


def tree_height(points: np.ndarray, ground_point: np.ndarray, ground_normal: np.ndarray, *,
                support_radius_m: float, min_support: int) -> float:
    """Tree height (m): distance along the ground normal from the local ground plane (ground_point (3,),
    unit-up ground_normal (3,), map frame) to the highest of the tree's points (N, 3) that has at least
    `min_support` other points within `support_radius_m` and does not lie on a level line (`_on_level_line`:
    a trellis wire running just above a crown joins its body). A flying point a depth camera leaves above the
    canopy has no support; NaN when no point qualifies."""
    h = height_above_plane(points, ground_point, ground_normal)  # (N,)
    if support_radius_m < 0 or min_support < 0:
        raise CanopyError(f"support radius and count must be >= 0, got {support_radius_m!r}, {min_support!r}")
    if len(h) == 0:
        return float("nan")
    if min_support == 0:
        return float(h.max())
    pts = np.asarray(points, float)
    n = _unit(ground_normal, "ground normal")
    order = np.argsort(-h, kind="stable")
    # Look at the highest candidates only: a KD-tree over the points within reach of them. Doubling the
    # candidate count when all of them are unsupported keeps this exact for any number of flying points.
    n_cand = min(len(h), 512)
    while True:
        cand = order[:n_cand]
        floor = h[cand[-1]] - support_radius_m
        near = order[: int(np.searchsorted(-h[order], -floor, side="right"))]
        counts = np.asarray(
            cKDTree(pts[near]).query_ball_point(pts[cand], support_radius_m, return_length=True)) - 1  # (C,)
        hit = np.nonzero(counts >= min_support)[0]
        if len(hit):
            # the line test reads points no lower than WIRE_BELOW_M under a candidate: those of `top` (whose
            # first n_cand are the candidates, in order)
            top = order[: int(np.searchsorted(-h[order], -(h[cand[-1]] - WIRE_BELOW_M), side="right"))]
            p_top, h_top = pts[top], h[top]
            tree = cKDTree(p_top)
            for k in hit:
                if not _on_level_line(p_top, h_top, tree, int(k), n):
                    return float(h[cand[k]])
        if n_cand == len(h):
            return float("nan")
        n_cand = min(len(h), 4 * n_cand)


# A trellis wire seen a few centimetres above a crown: within WIRE_REACH_M of a point on it the points form a
# line (second singular value under WIRE_LINEARITY of the first) lying within WIRE_LEVEL_DEG of level. A crown's
# top is a clump of leaves; a leader's tip is a line too, but upright. 10-tree standard row 31: the top of its end
# tree was 9 cm up such a wire (its 40 highest points spread 1.29 m along the row, 3 cm across).
WIRE_REACH_M = 0.2
WIRE_BELOW_M = 0.03  # m: the points no lower than this under the candidate (not the leaves the wire runs over)
WIRE_LINEARITY = 0.3  # the two sides' copies of a wire lie 2-3 cm apart after the merge: 0.16-0.22 there
WIRE_LEVEL_DEG = 30.0


def _on_level_line(pts: np.ndarray, h: np.ndarray, tree: cKDTree, i: int, up: np.ndarray) -> bool:
    """Whether point i of pts (N, 3), h (N,) m above the ground, lies on a level line (module constants
    WIRE_*); tree: a KD-tree of pts."""
    idx = np.asarray(tree.query_ball_point(pts[i], WIRE_REACH_M), np.int64)
    near = pts[idx[h[idx] >= h[i] - WIRE_BELOW_M]]  # (M, 3)
    if len(near) < 5:
        return False
    _, sv, vt = np.linalg.svd(near - near.mean(axis=0), full_matrices=False)
    return bool(sv[1] < WIRE_LINEARITY * sv[0] and abs(vt[0] @ up) < np.sin(np.radians(WIRE_LEVEL_DEG)))


def canopy_base_height(points: np.ndarray, ground_point: np.ndarray, ground_normal: np.ndarray, *,
                       trunk_radius_m: float, body_cell_m: float, off_axis_m: float = 0.05, slice_m: float = 0.02,
                       min_fraction: float = 0.1, max_gap_slices: int = 2) -> float:
    """Clear trunk height (m above the local ground): where the canopy begins. The tree's points (N, 3) off
    its trunk (further than trunk_radius_m + off_axis_m from the axis: the line through ground_point (3,)
    along the unit-up ground_normal (3,)), of their main body (cells of body_cell_m), counted in slices of slice_m; from the fullest slice down, the
    canopy goes on while slices hold at least min_fraction of the median occupied slice's count (gaps of up to
    max_gap_slices allowed). NaN without off-axis points.

    Why not the trunk's own length: the detector's trunk goes on up the leader between the leaves, 0.1-0.5 m
    above where the branches begin (10-tree standard row: 0.76-1.10 m against 0.57-0.72 m true)."""
    h = height_above_plane(points, ground_point, ground_normal)  # (N,)
    n = _unit(ground_normal, "ground normal")
    d = np.asarray(points, float) - np.asarray(ground_point, float).reshape(3)
    off = np.linalg.norm(d - h[:, None] * n, axis=1)  # (N,) m from the trunk axis
    away = (off > trunk_radius_m + off_axis_m) & (h > 0)
    if not away.any():
        return float("nan")
    # the crown's own body, its largest part alone: weeds and grass under it touch it only through the trunk,
    # which is left out here, and a lawn can hold more than a tenth of a crown's points
    hc = h[away][main_body(np.asarray(points, float)[away], body_cell_m, min_fraction=1.0)]
    counts = np.bincount(np.floor(hc / slice_m).astype(np.int64))  # (S,) per slice, from the ground up
    thr = min_fraction * float(np.median(counts[counts > 0]))
    full = counts >= max(thr, 1.0)
    start = int(np.argmax(counts))  # the fullest slice: inside the canopy whatever its top looks like
    base, gap = start, 0
    for s in range(start - 1, -1, -1):
        if full[s]:
            base, gap = s, 0
        else:
            gap += 1
            if gap > max_gap_slices:
                break
    return base * slice_m


def main_body(points: np.ndarray, cell_m: float, min_fraction: float = 0.1) -> np.ndarray:
    """(N,) bool: the points (N, 3) of the tree's body: the connected parts (cells of cell_m touching by a
    face, edge or corner) holding at least min_fraction of the largest part's points (the paper drops
    regions under 10 % of the principal one). What is left floats apart from the tree: a wire's stub at a
    post, a neighbour's stray leaf (10-tree standard row: a wire fragment 19 cm above the shortest crown made
    its height 21 cm too much). Keeping the largest part alone lost a third of a crown that wind had blurred
    into two parts (wind row, one tree: volume -31 %)."""
    pts = _check_points(points, "points")
    if len(pts) == 0:
        return np.zeros(0, bool)
    ijk = np.floor((pts - pts.min(axis=0)) / cell_m).astype(np.int64)  # (N, 3)
    grid = np.zeros(tuple(ijk.max(axis=0) + 1), bool)
    grid[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    labels, n = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
    lab = labels[ijk[:, 0], ijk[:, 1], ijk[:, 2]]  # (N,) >= 1
    size = np.bincount(lab)  # (n + 1,) points per part
    return size[lab] >= min_fraction * size.max()


def canopy_volume(points: np.ndarray, ground_point: np.ndarray, ground_normal: np.ndarray, *,
                  clear_trunk_height_m: float, alpha_m: float, body_cell_m: float | None = None,
                  voxel_m: float = 0.0) -> float:
    """Canopy volume (m^3): the alpha-complex volume of the tree's points (N, 3) higher than
    clear_trunk_height_m above its local ground plane (ground_point (3,), unit-up normal (3,)); with
    body_cell_m, of their main body only (main_body); with voxel_m > 0, thinned to that first. NaN when no
    point lies above the clear trunk (no crown was seen)."""
    pts = np.asarray(points, float)
    crown = pts[height_above_plane(pts, ground_point, ground_normal) > clear_trunk_height_m]
    if len(crown) == 0:
        return float("nan")
    if body_cell_m is not None:
        crown = crown[main_body(crown, body_cell_m)]
    if voxel_m > 0:
        crown = voxel_downsample(crown, voxel_m)[0]
    return alpha_complex_volume(crown, alpha_m)


def mirrored_share(own: np.ndarray, other: np.ndarray, trunk_point: np.ndarray, along: np.ndarray,
                   reach_m: float) -> np.ndarray:
    """(M,) bool over a neighbour's points other (M, 3): those lying where this tree's crown would reach if it
    were as wide towards the neighbour as away from it, i.e. within reach_m of the mirror image of this tree's
    own points (N, 3) on the far side from the neighbour, mirrored across the plane through trunk_point (3,)
    normal to along (3,), the row direction. Where crowns interlock a split of the points gives the shared
    leaves to one tree only; a tree's own alpha shape (the volume's definition) holds them too."""
    own = _check_points(own, "own points")
    other = _check_points(other, "neighbour points")
    if len(own) == 0 or len(other) == 0 or not reach_m > 0:
        return np.zeros(len(other), bool)
    d = _unit(along, "row direction")
    p0 = np.asarray(trunk_point, float).reshape(3)
    towards = np.sign(np.median((other - p0) @ d))  # the neighbour's side of the trunk
    s_own = (own - p0) @ d  # (N,) m along the row from the trunk
    far = own[s_own * towards < 0]
    if len(far) == 0:
        return np.zeros(len(other), bool)
    mirrored = far - 2.0 * np.outer((far - p0) @ d, d)  # (F, 3)
    dist, _ = cKDTree(mirrored).query(other, distance_upper_bound=reach_m)
    return np.isfinite(dist)


def voxel_downsample(points: np.ndarray, voxel_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(centroids (V, 3), voxel of each input point (N,)): one point per occupied cubic voxel of side
    voxel_m (m), the mean of its points. voxel_m <= 0 keeps every point."""
    pts = _check_points(points, "points")
    if not voxel_m > 0:
        return pts.copy(), np.arange(len(pts))
    if len(pts) == 0:
        return pts.copy(), np.zeros(0, np.int64)
    ijk = np.floor((pts - pts.min(axis=0)) / voxel_m).astype(np.int64)  # (N, 3) >= 0
    dims = ijk.max(axis=0) + 1
    key = (ijk[:, 0] * dims[1] + ijk[:, 1]) * dims[2] + ijk[:, 2]  # (N,) linear voxel index
    _, inv = np.unique(key, return_inverse=True)
    inv = inv.reshape(-1)
    n = np.bincount(inv).astype(float)  # (V,)
    cen = np.stack([np.bincount(inv, weights=pts[:, k]) for k in range(3)], axis=1) / n[:, None]  # (V, 3)
    return cen, inv
