"""Trunk cylinders from silhouettes alone (colour-only sides: no dense depth).

A trunk's left and right outline in one calibrated view are two image lines; each spans a plane
through the camera centre that touches the trunk (a tangent plane). A straight cylinder touches all
the tangent planes of all its views: the axis lies at distance r on the trunk's side of every one of
them, along the whole visible segment. Two views from different places fix the axis and the radius
(paper: the 2D term of eq. objectCylinder, here without the depth terms); more views average the
mask's edge noise.

Outline lines, not per-row edge rays: a learned mask's edge wanders a pixel or two from row to row and
leaves or weeds notch it; a line fitted robustly over the band's rows keeps the straight part and drops
the notches (rows more than `max_edge_px` off the line are left out and the line refitted).

Frames: each view carries T_map_cam of its camera (colour optical frame: x right, y down, z forward);
the cylinder comes out in `map`, in the map's units (metres for RGB-D poses; the map's own scale for a
colour-only side). Pixels are px, the pixel centre at integer coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from orchard_mapping.core.cylinder import Cylinder, CylinderError, perpendicular_basis
from orchard_mapping.core.types import CameraIntrinsics

__all__ = ["TangentPlane", "cylinder_from_silhouettes", "outline_planes"]


@dataclass(frozen=True)
class TangentPlane:
    """A plane through a camera centre touching the trunk: n . X + d = 0 in map, n unit, pointing into the
    trunk (the axis lies at n . X + d = +r)."""

    normal: np.ndarray  # (3,) unit, map
    offset: float  # d, map units
    view: int  # index of the view it came from
    side: int  # -1 the left outline, +1 the right one


def _edge_columns(mask: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows kept (R,), left edge u (R,), right edge u (R,)) px: the pixel borders of the widest run of
    mask pixels in each row (the trunk, not a stray blob beside it)."""
    keep, left, right = [], [], []
    for v in rows:
        cols = np.flatnonzero(mask[v])
        if len(cols) == 0:
            continue
        breaks = np.flatnonzero(np.diff(cols) > 1)
        starts = np.r_[cols[0], cols[breaks + 1]]
        ends = np.r_[cols[breaks], cols[-1]]
        i = int(np.argmax(ends - starts))
        if starts[i] == 0 or ends[i] == mask.shape[1] - 1:
            continue  # cut by the image border: not the trunk's outline
        keep.append(v)
        left.append(starts[i] - 0.5)
        right.append(ends[i] + 0.5)
    return np.asarray(keep, int), np.asarray(left, float), np.asarray(right, float)


def _robust_line(v: np.ndarray, u: np.ndarray, max_edge_px: float, min_rows: int) -> tuple[float, float] | None:
    """(a, b) of u = a v + b fitted to the rows, those more than max_edge_px off dropped and the line refitted
    (three rounds); None when fewer than min_rows rows are left."""
    sel = np.ones(len(v), bool)
    a = b = 0.0
    for _ in range(3):
        if sel.sum() < min_rows:
            return None
        a, b = np.polyfit(v[sel], u[sel], 1)
        r = np.abs(u - (a * v + b))
        # the median residual sets the scale: a notch (leaf, weed) is far off, edge jitter is not
        sel = r <= max(max_edge_px, 3.0 * float(np.median(r[sel])))
    return (float(a), float(b)) if sel.sum() >= min_rows else None


def outline_planes(mask: np.ndarray, T_map_cam: np.ndarray, intr: CameraIntrinsics, rows: tuple[int, int], view: int,
                   *, max_edge_px: float = 1.5, min_rows: int = 8) -> list[TangentPlane]:
    """The tangent planes of a trunk's left and right outline between image rows rows[0]..rows[1] (inclusive)
    of its mask (H, W) bool in a camera at T_map_cam (4, 4); none for an outline too short or notched."""
    m = np.asarray(mask, bool)
    v0, v1 = max(0, int(rows[0])), min(m.shape[0] - 1, int(rows[1]))
    v, ul, ur = _edge_columns(m, np.arange(v0, v1 + 1))
    K = np.array([[intr.fx, 0.0, intr.cx], [0.0, intr.fy, intr.cy], [0.0, 0.0, 1.0]])
    R, c = T_map_cam[:3, :3], T_map_cam[:3, 3]
    if len(v) == 0:
        return []
    # into the trunk: the ray through the outline's middle row at the trunk's centre column
    um, vm = float(np.median(0.5 * (ul + ur))), float(np.median(v))
    inside = np.array([(um - intr.cx) / intr.fx, (vm - intr.cy) / intr.fy, 1.0])
    out = []
    for side, u in ((-1, ul), (1, ur)):
        line = _robust_line(v, u, max_edge_px, min_rows)
        if line is None:
            continue
        a, b = line
        l_img = np.array([1.0, -a, -b])  # u - a v - b = 0
        n_cam = K.T @ l_img  # the plane through the centre that projects onto the line
        n_cam /= np.linalg.norm(n_cam)
        if n_cam @ inside < 0:
            n_cam = -n_cam
        n = R @ n_cam
        out.append(TangentPlane(n, float(-n @ c), view, side))
    return out


def _initial_axis(planes: list[TangentPlane], up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(axis (3,), point (3,)): the axis lies in every view's bisector plane (halfway between its left and
    right outline planes): their common direction and the point nearest all of them."""
    by_view: dict[int, dict[int, TangentPlane]] = {}
    for p in planes:
        by_view.setdefault(p.view, {})[p.side] = p
    bis = []
    for pair in by_view.values():
        if len(pair) == 2:
            # points equidistant from both planes (with the signs into the trunk): (n_l - n_r) . X + d_l - d_r = 0
            n = pair[-1].normal - pair[1].normal
            s = float(np.linalg.norm(n))
            if s > 1e-9:
                bis.append((n / s, (pair[-1].offset - pair[1].offset) / s))
    if len(bis) < 2:
        raise CylinderError(f"silhouette cylinder: {len(bis)} view(s) with both outlines; two are needed")
    N = np.array([b[0] for b in bis])  # (V, 3)
    D = np.array([b[1] for b in bis])  # (V,)
    # the axis direction: the least-squares null direction of the bisector normals, oriented up
    _, _, Vt = np.linalg.svd(N)
    a = Vt[-1] if Vt[-1] @ up >= 0 else -Vt[-1]
    # the point: on every bisector plane; where along the axis is free (a . X = 0 fixes it; the caller's
    # origin_hint moves it to the band)
    A = np.vstack([N, a[None]])
    X, *_ = np.linalg.lstsq(A, np.r_[-D, 0.0], rcond=None)
    return a, X


def cylinder_from_silhouettes(planes: list[TangentPlane], segment: tuple[float, float] = (-0.08, 0.08), *,
                              origin_hint: np.ndarray | None = None, up: np.ndarray | None = None,
                              huber_scale: float = 0.002) -> tuple[Cylinder, np.ndarray]:
    """The straight cylinder that touches every tangent plane along its segment: (cylinder, residuals (2P,)
    map units). segment (t0, t1): where along the axis, from the cylinder's origin, the outlines were taken
    (the band); origin_hint (3,): a point near where the origin should be along the axis (e.g. the band's
    height), else the least-squares point; up (3,): which way the axis points (map z when None). Residual
    of plane i at t: n_i . (O + t a) + d_i - r (Huber, huber_scale in map units). Needs two views that each
    give both outlines."""
    if len(planes) < 4:
        raise CylinderError(f"silhouette cylinder: {len(planes)} tangent planes; four (two views) are needed")
    a0, X0 = _initial_axis(planes, np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float))
    if origin_hint is not None:
        X0 = X0 + ((np.asarray(origin_hint, float) - X0) @ a0) * a0
    Nn = np.array([p.normal for p in planes])  # (P, 3)
    Dd = np.array([p.offset for p in planes])  # (P,)
    r0 = float(np.median(Nn @ X0 + Dd))
    if not np.isfinite(r0) or r0 <= 0:
        raise CylinderError(f"silhouette cylinder: the outlines meet on the wrong side of the axis (r0 = {r0:.4f})")
    e1, e2 = perpendicular_basis(a0)
    ts = np.asarray(segment, float)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        a = a0 + x[0] * e1 + x[1] * e2
        a /= np.linalg.norm(a)
        return a, X0 + x[2] * e1 + x[3] * e2, r0 + x[4]

    def residuals(x: np.ndarray) -> np.ndarray:
        a, O, r = unpack(x)
        Q = O[None] + ts[:, None] * a[None]  # (2, 3) the segment's ends on the axis
        return ((Nn @ Q.T) + Dd[:, None] - r).ravel()  # (2P,)

    sol = least_squares(residuals, np.zeros(5), loss="huber", f_scale=huber_scale, method="trf",
                        x_scale=[0.05, 0.05, 0.01, 0.01, 0.005])
    a, O, r = unpack(sol.x)
    if r <= 0:
        raise CylinderError(f"silhouette cylinder: radius {r:.4f} <= 0 after the fit")
    return Cylinder(a, O, float(r)), residuals(sol.x)
