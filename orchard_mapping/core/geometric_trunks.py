"""Trunks found from geometry alone: vertical, round columns rising from the ground of one side's fused cloud.

The trunk detector knows trunks by their look, and a look it was not trained on (grey or white-painted bark,
another renderer, a real camera) loses them. A trunk's shape does not change with its look: below the canopy
it is the one structure of the row that is vertical, round, 4-25 cm across and continuous from the ground up
to the first branches. This module finds such columns in the fused cloud of one side, with no image:

1. Ground height: the low percentile of the cloud's height in 25 cm cells across the row's plane, then the
   lowest of each cell's neighbours (a cell under the canopy or filled by a trunk takes its neighbours'
   ground).
2. The trunk band: points between BAND_LO_M and BAND_HI_M above that ground. Cells of 1 cm (top view) that
   hold points in most of the band's 4 cm height slices are columns (a trunk's surface seen from one side
   is an arc of such cells; leaves and weeds fill few slices of a cell).
3. Each connected group of column cells, small enough to be a trunk, is fitted with a circle in the top view
   (algebraic fit, then geometric Gauss-Newton): a trunk is round (residual RMS), seen over an arc
   (coverage) that faces the cameras (the centre lies beyond the arc), and its axis is vertical (the circles
   of the band's lower and upper halves agree).
4. Above the band: a trunk tapers and branches into the canopy; a trellis post goes on straight and bare
   to well above the cameras. A column whose shell of the same radius stays filled to POST_MIN_TOP_M and
   that is still one circle of about its radius at UPPER_SLICE_M is flagged `post_like`; one whose shell ends
   below that height with something seen above it, or whose points there fit no circle of its radius (a leader
   with branches and leaves), is `tree_like`. A column that is neither (a straight column of its radius, but too noisy to call bare) is left
   to the detector.

The pipeline (`orchard_mapping.pipeline`) turns each candidate the detector missed into trunk views: in the
keyframes that see it, the depth pixels on its cylinder form a mask (`cylinder_mask`), and the trunk is then
modelled like a detected one (eq. objectCylinder, local ground, the merge).

Frames: the side's odom frame, metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from orchard_mapping.core.alignment_types import AlignmentParams
from orchard_mapping.core.canonical_frame import canonical_frame
from orchard_mapping.core.detection import CLASS_TRUNK, Detection
from orchard_mapping.core.geometry import transform_points
from orchard_mapping.core.odometry import backproject
from orchard_mapping.core.trees import row_direction
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import AlignmentError

__all__ = ["TrunkCandidate", "column_detections", "columns_to_model", "cylinder_mask", "detection_places",
           "find_trunk_candidates", "mask_place", "on_tree_column", "row_frame"]

GROUND_CELL_M = 0.25  # m, cells of the ground height
GROUND_PERCENTILE = 5.0  # the ground is the low end of a cell's heights (flying pixels are rarer than 5 %)
BAND_LO_M = 0.12  # m above the ground: grass and the trunk's flare stay below
BAND_HI_M = 0.50  # m: below the first branches (clear trunk 0.55-0.75 m on apple rows)
SLICE_M = 0.04  # m, height slices of the band
COLUMN_CELL_M = 0.02  # m, top-view cells of the band
COLUMN_MIN_FILL = 0.5  # share of the band's slices a column cell must hold points in
RADIUS_RANGE_M = (0.015, 0.125)  # m, trunks 3-25 cm across
MAX_CLUSTER_M = 0.30  # m, a group of column cells wider than this is a hedge, wall or weed mass
MIN_ARC_DEG = 80.0  # deg of the circle the arc covers (one side sees up to 180)
MAX_RMS_FRACTION = 0.3  # circle residual RMS, of the radius (and at least MIN_RMS_M)
MIN_RMS_M = 0.009
MAX_TILT_DEG = 20.0  # deg, axis vs up
POST_MIN_TOP_M = 1.4  # m: a bare, straight column of one radius this high is a post
UPPER_SLICE_M = (0.9, 1.3)  # m above the ground: where a post-like column's circle is fitted again
# A post's circle there: the band's radius within 25 % (weeds at a post's foot widen its band circle: 48 vs 60 mm
# on slope_weeds) and a residual RMS within 10 mm (or 20 % of the radius). A trunk's leader, branches and leaves
# there fit no circle: 6-tree standard and slope_weeds rows (seeds 3, 4), every trunk 13.7-21.5 mm RMS but one
# (8.7 mm, its circle 1.8 times the band's); every post 2.0-9.2 mm.
POST_RADIUS_CHANGE = 0.25
# Tree-like there: no circle of the band's radius (the two trunks of those rows whose circle there kept their
# radius within 25 % spread 21.4 and 21.5 mm); between the post and tree limits the detector decides.
TREE_RMS_FACTOR = 2.0
POST_MAX_RMS_M = 0.010
POST_MAX_RMS_FRACTION = 0.2
MASK_TOP_M = 0.9  # m above the ground: a column's mask ends here (the clear trunk and a little of the leader)
MASK_GROW_PX = 1  # px each way: the depth pixels on a column end 1-2 px short of its silhouette (no depth at the edge);
# std6 row, geometry alone: diameter bias -1.78 mm as they are, +0.60 grown by 1 px, +2.5 by 2 (the edge snap does the rest)


@dataclass(frozen=True)
class TrunkCandidate:
    """A vertical round column of the fused cloud (a trunk or a post)."""

    base: np.ndarray  # (3,) m odom, where the axis meets the ground
    axis: np.ndarray  # (3,) unit, up the column
    up: np.ndarray  # (3,) unit, the side's up
    radius_m: float
    top_m: float  # m above the ground: where the shell of this radius stops being filled
    arc_deg: float  # deg of the circle seen
    rms_m: float  # circle residual RMS, m
    n_points: int  # band points on the column
    post_like: bool  # straight, untapered and bare to POST_MIN_TOP_M
    tree_like: bool  # ends below POST_MIN_TOP_M, or tapers or branches into clutter above the band
    lateral_m: float  # m across the row from the camera path (positive: away from the cameras)

    def axis_point(self, height_m: float) -> np.ndarray:
        """(3,) the axis point height_m above the ground."""
        return self.base + height_m / float(self.axis @ self.up) * self.axis


def row_frame(points: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(3, 3) rows: along the row, across it (from the cameras towards the row), up; from the side's fused
    cloud (P, 3) and camera poses (K, 4, 4) T_odom_cam. Up is the normal of the side's ground plane and
    along its cloud's first principal direction (the initial alignment's canonical frame): the cameras' own
    mean up is off by their mean pitch (19 deg on a side with a raised sweep looking down)."""
    cf = canonical_frame(points, poses, "front", AlignmentParams(), np.random.default_rng(0))
    along, up = cf.T_canon_odom[0, :3], cf.T_canon_odom[1, :3]
    across = np.cross(up, along)
    if across @ poses[:, :3, 2].mean(axis=0) < 0:
        across = -across
    return np.stack([along, across, up])


def _cell_low(a: np.ndarray, b: np.ndarray, h: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray,
                                                                                   np.ndarray]:
    """The ground height grid: (ground (A, B) m, +inf where unknown; a0, b0 the grid's origin as (1,) arrays)."""
    a0, b0 = a.min(), b.min()
    ia = ((a - a0) / cell).astype(np.int64)
    ib = ((b - b0) / cell).astype(np.int64)
    A, B = ia.max() + 1, ib.max() + 1
    key = ia * B + ib
    order = np.lexsort((h, key))
    ks, hs = key[order], h[order]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    counts = np.diff(np.r_[starts, len(ks)])
    pick = starts + (counts * GROUND_PERCENTILE / 100.0).astype(np.int64)
    low = np.full(A * B, np.inf)
    enough = counts >= 10
    low[ks[starts[enough]]] = hs[pick[enough]]
    grid = ndimage.minimum_filter(low.reshape(A, B), size=3, mode="constant", cval=np.inf)
    return grid, np.array([a0]), np.array([b0])


def _fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """(xc, yc, r, rms) of points (x, y): `_fit_circle_once`, then again on the points within 2.5 RMS of that
    circle (a leaf or weed touching the column is not part of it)."""
    xc, yc, r, rms = _fit_circle_once(x, y)
    keep = np.abs(np.hypot(x - xc, y - yc) - r) < 2.5 * rms
    if 10 <= keep.sum() < len(x):
        xc, yc, r, rms = _fit_circle_once(x[keep], y[keep])
    return xc, yc, r, rms


def _fit_circle_once(x: np.ndarray, y: np.ndarray, iterations: int = 10) -> tuple[float, float, float, float]:
    """(xc, yc, r, rms) of points (x, y): algebraic (Kasa) start, then geometric Gauss-Newton."""
    A = np.stack([2 * x, 2 * y, np.ones_like(x)], axis=1)  # (N, 3)
    sol, *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    xc, yc = sol[0], sol[1]
    r = float(np.sqrt(max(sol[2] + xc * xc + yc * yc, 1e-12)))
    for _ in range(iterations):
        dx, dy = x - xc, y - yc
        d = np.hypot(dx, dy) + 1e-12
        res = d - r  # (N,)
        J = np.stack([-dx / d, -dy / d, -np.ones_like(d)], axis=1)  # (N, 3) d res / d (xc, yc, r)
        step, *_ = np.linalg.lstsq(J, -res, rcond=None)
        xc, yc, r = xc + step[0], yc + step[1], r + step[2]
        if np.abs(step).max() < 1e-6:
            break
    rms = float(np.sqrt(np.mean((np.hypot(x - xc, y - yc) - r) ** 2)))
    return float(xc), float(yc), float(abs(r)), rms


def _arc_deg(x: np.ndarray, y: np.ndarray, xc: float, yc: float) -> float:
    """Degrees of the circle around (xc, yc) that points (x, y) cover, in 10 deg bins."""
    ang = np.degrees(np.arctan2(y - yc, x - xc)) % 360.0
    return 10.0 * len(np.unique((ang // 10).astype(int)))


def find_trunk_candidates(points: np.ndarray, poses: np.ndarray) -> list[TrunkCandidate]:
    """Vertical round columns (trunks or posts) of a side's fused cloud points (P, 3) odom, seen from the
    keyframes poses (K, 4, 4) T_odom_cam; ordered along the row."""
    P = np.asarray(points, float)
    if len(P) < 100 or len(poses) < 2:
        return []
    try:
        R = row_frame(P, np.asarray(poses, float))  # rows: along, across, up
    except AlignmentError:  # no ground plane: no ground to rise from
        return []
    along, across, up = R
    Q = P @ R.T  # (P, 3) along, across, up
    a, b, h = Q[:, 0], Q[:, 1], Q[:, 2]
    ground, a0, b0 = _cell_low(a, b, h, GROUND_CELL_M)
    ia = np.clip(((a - a0) / GROUND_CELL_M).astype(np.int64), 0, ground.shape[0] - 1)
    ib = np.clip(((b - b0) / GROUND_CELL_M).astype(np.int64), 0, ground.shape[1] - 1)
    g = ground[ia, ib]  # (P,) ground height under each point
    hg = h - g
    band = np.flatnonzero(np.isfinite(hg) & (hg > BAND_LO_M) & (hg < BAND_HI_M))
    if len(band) < 50:
        return []
    n_slices = int(round((BAND_HI_M - BAND_LO_M) / SLICE_M))
    ca = ((a[band] - a0[0]) / COLUMN_CELL_M).astype(np.int64)
    cb = ((b[band] - b0[0]) / COLUMN_CELL_M).astype(np.int64)
    sl = np.minimum(((hg[band] - BAND_LO_M) / SLICE_M).astype(np.int64), n_slices - 1)
    CA, CB = ca.max() + 1, cb.max() + 1
    cell = ca * CB + cb
    filled = np.unique(cell * n_slices + sl) // n_slices  # one entry per (cell, slice) holding points
    fill = np.bincount(filled, minlength=CA * CB).reshape(CA, CB) / n_slices
    column = fill >= COLUMN_MIN_FILL
    labels, n = ndimage.label(ndimage.binary_dilation(column, np.ones((3, 3), bool)), np.ones((3, 3), int))
    if n == 0:
        return []
    lab_of_point = labels[ca, cb] * column[ca, cb]  # (Nb,) 0: not on a column cell
    # the camera path in the row frame, for which side of an arc faces the cameras
    cam = poses[:, :3, 3] @ R.T  # (K, 3)
    out: list[TrunkCandidate] = []
    for k, sl_obj in enumerate(ndimage.find_objects(labels), start=1):
        if sl_obj is None:
            continue
        if max(sl_obj[0].stop - sl_obj[0].start, sl_obj[1].stop - sl_obj[1].start) * COLUMN_CELL_M > MAX_CLUSTER_M:
            continue
        idx = band[lab_of_point == k]
        if len(idx) < 60:
            continue
        x, y, z = a[idx], b[idx], hg[idx]
        xc, yc, r, rms = _fit_circle(x, y)
        if not (RADIUS_RANGE_M[0] <= r <= RADIUS_RANGE_M[1]) or rms > max(MIN_RMS_M, MAX_RMS_FRACTION * r):
            continue
        arc = _arc_deg(x, y, xc, yc)
        if arc < MIN_ARC_DEG:
            continue
        # the arc faces the cameras: the cameras near it along the row lie on the arc's side of the centre
        near_cam = cam[np.abs(cam[:, 0] - xc) < 1.0]
        if len(near_cam) == 0:
            continue
        if (np.mean(y) - yc) * (np.median(near_cam[:, 1]) - yc) <= 0:
            continue
        mid = 0.5 * (BAND_LO_M + BAND_HI_M)
        lo, hi = z < mid, z >= mid
        if lo.sum() < 20 or hi.sum() < 20:
            continue
        x1, y1, r1, _ = _fit_circle(x[lo], y[lo])
        x2, y2, r2, _ = _fit_circle(x[hi], y[hi])
        dz = float(np.mean(z[hi]) - np.mean(z[lo]))
        tilt = np.degrees(np.arctan2(np.hypot(x2 - x1, y2 - y1), max(dz, 1e-3)))
        if tilt > MAX_TILT_DEG or abs(r1 - r2) > 0.3 * r + 0.005:
            continue
        ax = np.array([(x2 - x1) / max(dz, 1e-3), (y2 - y1) / max(dz, 1e-3), 1.0])
        ax /= np.linalg.norm(ax)
        g0 = float(np.median(g[idx]))
        top, post_like, tree_like = _column_top(a, b, hg, xc, yc, r, ax)
        base_rf = np.array([xc, yc, g0 + mid]) - mid * ax / ax[2]  # down the axis from the band's middle
        lateral = float(yc - np.median(near_cam[:, 1]))
        out.append(TrunkCandidate(base=R.T @ base_rf, axis=R.T @ ax, up=up, radius_m=r, top_m=top,
                                  arc_deg=arc, rms_m=rms, n_points=len(idx), post_like=post_like,
                                  tree_like=tree_like,
                                  lateral_m=lateral))
    out.sort(key=lambda c: float(c.base @ along))
    return _dedup(out)


def _column_top(a: np.ndarray, b: np.ndarray, hg: np.ndarray, xc: float, yc: float, r: float, ax: np.ndarray
                ) -> tuple[float, bool, bool]:
    """(top m above the ground where the shell of radius r around the column stops being filled, post-like,
    tree-like).
    The shell is read in 5 cm slices upward from the band; a gap of three empty slices ends it. Post-like: the
    shell goes on to POST_MIN_TOP_M and the column keeps its radius there (UPPER_SLICE_M): a post is
    untapered, while a trunk's leader above the first branches is a fraction of its width."""
    s = (hg - 0.5 * (BAND_LO_M + BAND_HI_M)) / ax[2]
    dx = a - (xc + ax[0] * s)
    dy = b - (yc + ax[1] * s)
    d = np.hypot(dx, dy)
    above = (hg >= BAND_HI_M) & (hg < 3.0)
    shell = above & (np.abs(d - r) < max(0.01, 0.25 * r))
    step = 0.05
    occupied = np.zeros(int(np.ceil((3.0 - BAND_HI_M) / step)), bool)
    occupied[((hg[shell] - BAND_HI_M) / step).astype(np.int64)] = True
    top = BAND_HI_M
    gap = 0
    for i, o in enumerate(occupied):
        if o:
            top, gap = BAND_HI_M + (i + 1) * step, 0
        else:
            gap += 1
            if gap >= 3:
                break
    # Ended low: a trunk into its canopy if something is seen above it there; else perhaps the view ended (a
    # side recorded with a level sweep only sees 1.1 m up: its posts ended there on the 1-tree test row).
    ended_low = top < POST_MIN_TOP_M and int(np.sum((hg > top + 0.15) & (hg < 3.0) & (d < r + 0.15))) >= 20
    # The column's circle again above the band (lower where the shell ends lower, e.g. out of view).
    hi = min(UPPER_SLICE_M[1], top)
    lo = min(UPPER_SLICE_M[0], hi - 0.3)
    upper = (hg >= lo) & (hg < hi) & (d < r + 0.04)
    if lo < BAND_HI_M or upper.sum() < 30:
        return float(top), False, ended_low
    _, _, r_hi, rms_hi = _fit_circle(a[upper] - ax[0] * s[upper], b[upper] - ax[1] * s[upper])
    limit = max(POST_MAX_RMS_M, POST_MAX_RMS_FRACTION * r)
    same_radius = abs(r_hi - r) <= POST_RADIUS_CHANGE * r
    post_like = top >= POST_MIN_TOP_M and same_radius and rms_hi <= limit
    tree_like = ended_low or not same_radius or rms_hi > TREE_RMS_FACTOR * limit
    return float(top), bool(post_like), bool(tree_like)


def _dedup(cands: list[TrunkCandidate]) -> list[TrunkCandidate]:
    """One candidate per column: of candidates whose axes are closer than their radii plus 5 cm, the one with
    the most points."""
    keep: list[TrunkCandidate] = []
    for c in sorted(cands, key=lambda c: -c.n_points):
        if all(np.linalg.norm(c.base - k.base) > c.radius_m + k.radius_m + 0.05 for k in keep):
            keep.append(c)
    return [c for c in cands if any(c is k for k in keep)]


def cylinder_mask(cand: TrunkCandidate, depth: np.ndarray, T_odom_cam: np.ndarray, intr: CameraIntrinsics,
                  depth_sigma_coeff: float, top_m: float) -> np.ndarray | None:
    """(H, W) bool: the pixels of depth (H, W) m whose points lie on the candidate's cylinder between 5 cm above
    the ground and top_m, in the keyframe T_odom_cam; None when the column is not in view. The tolerance
    follows the depth noise at the column's range (2.5 sd of depth_sigma_coeff * z^2, at least 1.5 cm)."""
    H, W = depth.shape
    T_cam_odom = np.linalg.inv(T_odom_cam)
    up = cand.axis
    bottom = cand.axis_point(0.05)
    # sample the cylinder's surface to bound its image
    hs = np.linspace(0.0, top_m - 0.05, 8)
    t = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    s = np.cross(up, t)
    ang = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ring = cand.radius_m * (np.outer(np.cos(ang), t) + np.outer(np.sin(ang), s))  # (12, 3)
    X = (bottom[None, None] + hs[:, None, None] * up + ring[None]).reshape(-1, 3)
    Xc = X @ T_cam_odom[:3, :3].T + T_cam_odom[:3, 3]
    if np.any(Xc[:, 2] < 0.2):
        return None
    u = intr.fx * Xc[:, 0] / Xc[:, 2] + intr.cx
    v = intr.fy * Xc[:, 1] / Xc[:, 2] + intr.cy
    c0, c1 = int(np.floor(u.min())) - 3, int(np.ceil(u.max())) + 4
    r0, r1 = int(np.floor(v.min())) - 3, int(np.ceil(v.max())) + 4
    if c1 <= 0 or r1 <= 0 or c0 >= W or r0 >= H:
        return None
    # a column cut by the image's edge is left to frames that see it whole
    if c0 < 0 or c1 > W:
        return None
    r0, r1 = max(r0, 0), min(r1, H)
    sub = depth[r0:r1, c0:c1]
    vv, uu = np.nonzero(sub > 0)
    if len(vv) == 0:
        return None
    zz = sub[vv, uu].astype(float)
    po = transform_points(T_odom_cam, backproject(np.stack([uu + c0, vv + r0], axis=1), zz, intr))  # (M, 3) odom
    rel = po - bottom
    along_axis = rel @ up  # m above the mask's bottom
    radial = np.linalg.norm(rel - np.outer(along_axis, up), axis=1)
    tol = max(0.015, 2.5 * depth_sigma_coeff * float(np.median(zz)) ** 2)
    on = (np.abs(radial - cand.radius_m) < tol) & (along_axis >= 0.0) & (along_axis <= top_m - 0.05)
    mask = np.zeros((H, W), bool)
    mask[vv[on] + r0, uu[on] + c0] = True
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((5, 5), np.uint8))
    if MASK_GROW_PX:
        mask = cv2.dilate(mask, np.ones((1, 2 * MASK_GROW_PX + 1), np.uint8))
    mask = mask.astype(bool)
    return mask


ROW_LINE_TOLERANCE_M = 0.3  # m across the row: a column farther than this from the row line is not a tree of it


def columns_to_model(cands: list[TrunkCandidate], detected: np.ndarray, min_detections: int,
                     radius_m: float, only: bool) -> list[TrunkCandidate]:
    """The columns to model as trunks from geometry: not post-like, on the row line, and (unless `only`) not
    already a detector trunk. detected (N, 3) m odom: where each trunk detection lies (its depth pixels'
    median); a column with at least min_detections of them within radius_m (across the up direction) is the
    detector's. The row line runs along the principal direction of all the columns' feet (posts stand on it too),
    through the median across it of the columns the detector agrees on (of all tree-like columns when it agrees on
    fewer than two). Measured in the map, not from the camera: a camera path that wanders 0.2 m towards and away
    from the row (a second renderer's steady rows) put trees of one row 1.26-1.64 m from it, and trees fell off a
    line drawn from the cameras."""
    trees = [c for c in cands if c.tree_like]
    if not trees:
        return []
    up = trees[0].up

    def n_near(c: TrunkCandidate) -> int:
        if len(detected) == 0:
            return 0
        rel = detected - c.axis_point(0.3)
        return int(np.sum(np.linalg.norm(rel - np.outer(rel @ up, up), axis=1) < radius_m))

    agreed = [c for c in trees if n_near(c) >= min_detections]
    on_row = trees  # one column alone is its own row line
    if len(cands) >= 2:
        feet = np.array([c.base - (c.base @ up) * up for c in cands])  # (C, 3) m odom, across up
        across = np.cross(up, row_direction(feet))
        across /= np.linalg.norm(across)
        ref = float(np.median([c.base @ across for c in (agreed if len(agreed) >= 2 else trees)]))
        on_row = [c for c in trees if abs(float(c.base @ across) - ref) <= ROW_LINE_TOLERANCE_M]
    return on_row if only else [c for c in on_row if not any(c is a for a in agreed)]


def column_detections(cands: list[TrunkCandidate], depth: np.ndarray, T_odom_cam: np.ndarray,
                      intr: CameraIntrinsics, depth_sigma_coeff: float, min_pixels: int, max_range_m: float
                      ) -> list[Detection]:
    """The trunk detections that the columns cands make in one keyframe (depth (H, W) m, pose T_odom_cam):
    each column in view within max_range_m whose cylinder holds at least min_pixels depth pixels."""
    out = []
    T_cam_odom = np.linalg.inv(T_odom_cam)
    for c in cands:
        p = T_cam_odom[:3, :3] @ c.axis_point(0.3) + T_cam_odom[:3, 3]
        if not 0.3 < p[2] < max_range_m:
            continue
        mask = cylinder_mask(c, depth, T_odom_cam, intr, depth_sigma_coeff, min(c.top_m, MASK_TOP_M))
        if mask is not None and int(mask.sum()) >= min_pixels:
            out.append(Detection.from_mask(mask, CLASS_TRUNK, score=1.0, source="geometry"))
    return out


def mask_place(mask: np.ndarray, depth: np.ndarray, T_odom_cam: np.ndarray, intr: CameraIntrinsics
               ) -> np.ndarray | None:
    """(3,) m odom: the median of a mask's depth pixels (H, W) in the keyframe T_odom_cam (as trunk association
    places a detection); None without depth in the mask."""
    rows, cols = np.nonzero(np.asarray(mask) & (np.asarray(depth) > 0))
    if len(rows) == 0:
        return None
    z = np.asarray(depth)[rows, cols].astype(float)
    return np.median(transform_points(T_odom_cam, backproject(np.stack([cols, rows], axis=1), z, intr)), axis=0)


def detection_places(views: list, intr: CameraIntrinsics) -> np.ndarray:
    """(N, 3) m odom: each trunk detection of views (core.trunks.TrunkView) at its depth pixels' median."""
    places = [mask_place(det.mask, v.depth, v.T_odom_cam, intr) for v in views for det in v.detections
              if det.class_id == CLASS_TRUNK]
    return np.array([p for p in places if p is not None]).reshape(-1, 3)


def on_tree_column(place: np.ndarray | None, cands: list[TrunkCandidate], post_like: bool = False) -> bool:
    """Whether a detection placed at place (3,) m odom (None: no depth) lies on a tree-like column (a trunk by its
    shape: tapering or branching), or with post_like True on a post-like one: within the column's radius plus
    5 cm of its axis, across up (a post may stand a hand's width from a tree)."""
    if place is None:
        return False
    for c in cands:
        if not (c.post_like if post_like else c.tree_like):
            continue
        rel = place - c.axis_point(0.3)
        if np.linalg.norm(rel - (rel @ c.up) * c.up) < c.radius_m + 0.05:
            return True
    return False
