"""Depth and heading of the initial alignment from the trunks, in the top view (X, Z) (paper, "Alignment in
Depth Direction using Trunk Information"): trunk axes at the diameter height, paired across the sides and
fitted rigidly; and, with too few pairs, the fallback from each side's own trunk line.

Frames: the sides' canonical frames (core.canonical_frame); metres.
"""

from __future__ import annotations

import numpy as np

from orchard_mapping.core.alignment_types import AlignmentParams, AlignmentSide, CanonicalFrame, SideAlignment
from orchard_mapping.core.front_view import front_view_fit
from orchard_mapping.core.geometry import make_transform
from orchard_mapping.errors import AlignmentError

# --------------------------------------------------------------------------- trunks

def trunk_points(side: AlignmentSide, T: np.ndarray, height: float) -> np.ndarray:
    """(T, 3) each trunk axis at `height` above the ground, in the frame T maps odom to (canonical)."""
    base = side.trunk_base @ T[:3, :3].T + T[:3, 3]
    axis = side.trunk_axis @ T[:3, :3].T
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    s = (height - base[:, 1]) / np.where(np.abs(axis[:, 1]) > 0.2, axis[:, 1], 1.0)
    return base + s[:, None] * axis


def rigid_xz(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
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


def mutual_nearest(d: np.ndarray, radius: float) -> list[tuple[int, int, float]]:
    """(i, j, d_ij) for every i whose nearest j (in the distance matrix d (F, B)) has i as its nearest,
    closer than radius."""
    out = []
    for i in range(d.shape[0] if d.shape[1] else 0):
        j = int(np.argmin(d[i]))
        if d[i, j] < radius and int(np.argmin(d[:, j])) == i:
            out.append((i, j, float(d[i, j])))
    return out


def pair_trunk_points(pf: np.ndarray, pb: np.ndarray, radius: float) -> list[tuple[int, int, float]]:
    """Mutual nearest pairs of trunk points in the (X, Z) plane within radius: (i front, j back, gap)."""
    return mutual_nearest(np.linalg.norm(pf[:, None, [0, 2]] - pb[None, :, [0, 2]], axis=2), radius)  # (F, B)


def bend_free_gaps(pf: np.ndarray, pb: np.ndarray, params: AlignmentParams) -> np.ndarray:
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


def align_by_trunk_lines(dx0: float, Bf: np.ndarray, Bb: np.ndarray, tf: np.ndarray, tb: np.ndarray,
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
        S, s, b_rms, cpd_log, (x0, x1) = front_view_fit(dx0, Bf, Bb, scale_free, params)
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
    along = pair_trunk_points(tf * [1, 1, 0], tb_al * [1, 1, 0], 3 * params.pair_radius_m)
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
    near = pair_trunk_points(tf, tb_al, 3 * params.pair_radius_m)
    if near:  # trees seen from both sides (fewer than min_pairs): their trunks set the shift along the row, and
        # their feet (each on its side's ground under the tree) the height, which the front views set to a few cm
        S[0, 3] += float(np.median([tf[i, 0] - tb_al[j, 0] for i, j, _ in near]))
        foot_f = front.trunk_base @ cf.T_canon_odom[:3, :3].T + cf.T_canon_odom[:3, 3]
        foot_b = (back.trunk_base @ cb.T_canon_odom[:3, :3].T + cb.T_canon_odom[:3, 3]) @ S[:3, :3].T + S[:3, 3]
        S[1, 3] += float(np.median([foot_f[i, 1] - foot_b[j, 1] for i, j, _ in near]))
        tb_al = tb @ S[:3, :3].T + S[:3, 3]
    pairs = pair_trunk_points(tf, tb_al, params.pair_radius_m)
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
