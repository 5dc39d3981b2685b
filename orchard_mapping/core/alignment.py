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

Modules: the settings and results in core.alignment_types, step 1 in core.canonical_frame, step 2 in
core.front_view, step 3 and the fallback without trunk pairs in core.trunk_alignment; here the search over
shifts along the row that ties them together, and the ICP baseline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from orchard_mapping.core.alignment_types import AlignmentParams, AlignmentSide, SideAlignment
from orchard_mapping.core.canonical_frame import canonical_frame, thin_to_grid, voxel_centres
from orchard_mapping.core.front_view import front_view_boundary, front_view_fit
from orchard_mapping.core.trunk_alignment import (
    align_by_trunk_lines,
    bend_free_gaps,
    mutual_nearest,
    pair_trunk_points,
    rigid_xz,
    trunk_points,
)
from orchard_mapping.errors import AlignmentError

__all__ = [
    "AlignmentSide",
    "SideAlignment",
    "align_sides",
    "icp_merge",
    "pair_trunks",
    "shift_costs",
]


# m, trunk diameters closer than this vote fully for the shift that brings their trunks together: one side's
# diameter is 1-1.5 mm off the truth (MAE), trees of a row differ by centimetres
DIAMETER_VOTE_SIGMA_M = 0.003


# --------------------------------------------------------------------------- shift along the row

def shift_costs(Bf: np.ndarray, Bb: np.ndarray, params: AlignmentParams) -> tuple[np.ndarray, np.ndarray]:
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


def _from_shift(dx0: float, Bf: np.ndarray, Bb: np.ndarray, tf: np.ndarray, tb: np.ndarray, front: AlignmentSide,
                back: AlignmentSide, scale_free: bool, params: AlignmentParams, use_cpd: bool = True) -> _Candidate:
    """CPD of the front views from shift dx0 (or, use_cpd False, the shift as it is), then the top view from
    the trunks paired along the row."""
    S, s, b_rms, cpd_log, _ = front_view_fit(dx0, Bf, Bb, scale_free, params, use_cpd)
    log = [cpd_log]
    # Top view (X, Z): trunks paired along the row, then the rigid 2D fit of their axes (rotation about
    # Y, X and Z shift): the depth offset, and the yaw the front views cannot see.
    tb_al = tb @ S[:3, :3].T + S[:3, 3]
    near = pair_trunk_points(tf * [1, 1, 0], tb_al * [1, 1, 0], 3 * params.pair_radius_m)  # X only: Z still unknown
    if len(near) < params.min_pairs:
        raise AlignmentError(
            f"only {len(near)} trunk(s) seen from both sides (front {len(tf)}, back {len(tb)} trunks): "
            f"at least {params.min_pairs} are needed to merge the sides")
    i_f, i_b = [i for i, _, _ in near], [j for _, j, _ in near]
    keep = np.ones(len(near), bool)
    for _ in range(2):  # refit without pairs far off the first fit (a trunk paired with its neighbour's)
        G = rigid_xz(tb_al[np.array(i_b)[keep]], tf[np.array(i_f)[keep]])
        moved = tb_al[i_b] @ G[:3, :3].T + G[:3, 3]
        gap = np.linalg.norm((moved - tf[i_f])[:, [0, 2]], axis=1)
        keep = gap <= max(3 * np.median(gap), params.pair_radius_m / 3)
        if keep.sum() < params.min_pairs:
            keep[np.argsort(gap)[:params.min_pairs]] = True
    S = G @ S
    tb_al = tb @ S[:3, :3].T + S[:3, 3]
    pairs = pair_trunk_points(tf, tb_al, params.pair_radius_m)
    log.append(f"top view from {int(keep.sum())} of {len(near)} trunks paired along the row: rotation about Y "
               f"{np.degrees(np.arctan2(G[0, 2], G[0, 0])):+.2f} deg, depth offset {G[2, 3]:+.3f} m; "
               f"{len(pairs)} pairs within {params.pair_radius_m:g} m")
    if len(pairs) < params.min_pairs:
        raise AlignmentError(
            f"only {len(pairs)} trunk pair(s) agree after alignment (of {len(near)} matched along the row): "
            f"at least {params.min_pairs} are needed to merge the sides")
    gaps_mm = 1000 * bend_free_gaps(tf[[i for i, _, _ in pairs]], tb_al[[j for _, j, _ in pairs]], params)
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
    thin_f = voxel_centres(front.points, params.view_cell_m)  # (Q, 3) odom_front
    thin_b = voxel_centres(back.points, params.view_cell_m)
    cf = canonical_frame(thin_f, front.poses, "front", params, rng)
    cb = canonical_frame(thin_b, back.poses, "back", params, rng)
    Pf = thin_f @ cf.T_canon_odom[:3, :3].T + cf.T_canon_odom[:3, 3]
    Pb = thin_b @ cb.T_canon_odom[:3, :3].T + cb.T_canon_odom[:3, 3]
    tf = trunk_points(front, cf.T_canon_odom, params.trunk_height_m)
    tb = trunk_points(back, cb.T_canon_odom, params.trunk_height_m)
    zf = float(np.median(tf[:, 2])) if len(tf) else float(np.median(Pf[:, 2]))
    zb = float(np.median(tb[:, 2])) if len(tb) else float(np.median(Pb[:, 2]))
    Bf = front_view_boundary(Pf, zf, params, rng)
    Bb = front_view_boundary(Pb, zb, params, rng)
    if len(Bf) < 20 or len(Bb) < 20:
        raise AlignmentError(f"too little above the ground to align the sides' front views "
                             f"({len(Bf)} front, {len(Bb)} back boundary points)")
    # X shift: a row repeats itself every tree, so the front views alone may fit best one tree off (a
    # 9-tree partial_overlap row: 1.85 m off, silently). The best few shifts of eq. dist are each carried
    # through CPD and the top view; the one whose paired trunks agree best (gap of their axes, and their
    # diameters, which differ from tree to tree by centimetres) wins.
    shifts, cost = shift_costs(Bf, Bb, params)
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
        return align_by_trunk_lines(starts[0], Bf, Bb, tf, tb, front, back, cf, cb, scale_free, params, reason)
    tried.sort(key=lambda x: x[0])
    _, dx0, best = tried[0]
    if best.score_mm > params.max_disagreement_mm:
        reason = (f"the trunks the sides seem to share do not agree (best shift {dx0:+.2f} m along the row: median "
                  f"axis gap + diameter difference {best.score_mm:.1f} mm > {params.max_disagreement_mm:g} mm): "
                  "they are probably different trees (the sides cover different stretches of the row, or both "
                  "recordings are of the same side)")
        if params.fallback != "global_features":
            raise AlignmentError(reason)
        return align_by_trunk_lines(starts[0], Bf, Bb, tf, tb, front, back, cf, cb, scale_free, params, reason)
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


# --------------------------------------------------------------------------- baseline

def icp_merge(front: AlignmentSide, back: AlignmentSide, params: AlignmentParams, rng: np.random.Generator,
              max_distance_m: float = 0.30) -> np.ndarray:
    """The ICP baseline: point-to-plane ICP (Open3D) of the thinned clouds, started from the sides'
    canonical frames (ground and PCA: the sides facing each other) with the clouds' medians brought
    together. Returns T_front_back (4, 4). The paper reports that ICP fails here: the two
    sides see different surfaces of every tree."""
    import open3d as o3d

    # Each cloud thinned once to the canonical frame's grid (which then keeps every point of it).
    thin_f = thin_to_grid(np.asarray(front.points, float), params.voxel_m)  # (Q, 3) odom_front
    thin_b = thin_to_grid(np.asarray(back.points, float), params.voxel_m)
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
    return tuple((int(front.trunk_ids[i]), int(back.trunk_ids[j])) for i, j, _ in mutual_nearest(d, radius_m))

