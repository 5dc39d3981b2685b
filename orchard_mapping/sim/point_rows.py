"""Synthetic merged tree-row point clouds with per-point truth, for the traits stage's tests and benchmark.

Not the rendered simulator: each tree is a trunk cylinder and an ellipsoid canopy shell (the surface the two
sides' depth cameras see), on a tilted ground plane, with optional posts, flying points above the canopies
and a branch of one tree stretching over its neighbour's crown. A tree's shell points inside a neighbour's
ellipsoid are left out (hidden inside the union), so touching canopies meet along their intersection.
Frame: map, metres, z up; the row runs along x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["KIND_FLYING", "KIND_GROUND", "KIND_POST", "KIND_TREE", "SyntheticRow", "synthetic_row"]

KIND_TREE, KIND_GROUND, KIND_POST, KIND_FLYING = 0, 1, 2, 3
TRUNK_RADIUS_M = 0.04
POST_RADIUS_M = 0.04
POST_HEIGHT_M = 2.6
BRANCH_GAP_M = 0.10  # m, clump of the over-reaching branch above the neighbour's crown (free, not touching)


@dataclass(frozen=True)
class SyntheticRow:
    points: np.ndarray  # (N, 3) m, map
    tree: np.ndarray  # (N,) int, true tree of each point, -1 ground / post
    kind: np.ndarray  # (N,) int, KIND_*
    trunk_positions: np.ndarray  # (T, 3) m, where each trunk axis meets its local ground
    ground_points: np.ndarray  # (T, 3) m, = trunk_positions (a point of each local ground plane)
    ground_normals: np.ndarray  # (T, 3) unit, up
    clear_heights: np.ndarray  # (T,) m above local ground, canopy bottom
    heights: np.ndarray  # (T,) m, highest tree point above its local ground (flying points excluded)
    post_points: np.ndarray  # (P, 3) m, post foot on the ground
    post_radius_m: float  # m


def _ellipsoid_shell(rng: np.random.Generator, n: int, radii: np.ndarray, thickness: float) -> np.ndarray:
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * radii * rng.uniform(1.0 - thickness, 1.0, (n, 1))  # (n, 3) about the centre


def _cylinder(rng: np.random.Generator, n: int, foot: np.ndarray, top: np.ndarray, r: float) -> np.ndarray:
    axis = top - foot
    u = np.cross(axis, [0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 * np.linalg.norm(axis) else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(axis / np.linalg.norm(axis), u)
    t = rng.uniform(0, 1, (n, 1))
    a = rng.uniform(0, 2 * np.pi, (n, 1))
    return foot + t * axis + r * (np.cos(a) * u + np.sin(a) * w)


def synthetic_row(seed: int, n_trees: int = 3, spacing_m: float = 0.7, *,
                  radius_along_m: tuple[float, float] = (0.45, 0.55), radius_across_m: tuple[float, float] = (0.35, 0.45),
                  radius_up_m: tuple[float, float] = (0.5, 0.7), clear_m: tuple[float, float] = (0.5, 0.7),
                  points_per_m2: float = 4000.0, interior_fraction: float = 0.1, branch_over: tuple[int, ...] = (),
                  posts_between: tuple[int, ...] = (), n_flying: int = 0, slope_deg: tuple[float, float] = (0.0, 0.0),
                  noise_m: float = 0.003) -> SyntheticRow:
    """A row of n_trees trees spacing_m apart (jittered by 5 %). branch_over: trees whose branch (with a leaf
    clump at its end) reaches over the next tree's crown; posts_between: i puts a post half way between
    trees i and i + 1; n_flying: isolated points 0.3-1 m above random canopies; slope_deg: ground tilt
    along and across the row."""
    rng = np.random.default_rng(seed)
    sx, sy = np.tan(np.radians(slope_deg))
    n = np.array([-sx, -sy, 1.0])
    n /= np.linalg.norm(n)
    ground_z = lambda x, y: sx * x + sy * y  # noqa: E731
    xs = np.arange(n_trees) * spacing_m + rng.normal(0, 0.05 * spacing_m, n_trees)
    ys = rng.normal(0, 0.02, n_trees)
    feet = np.stack([xs, ys, ground_z(xs, ys)], 1)  # (T, 3)
    radii = np.stack([rng.uniform(*radius_along_m, n_trees), rng.uniform(*radius_across_m, n_trees),
                      rng.uniform(*radius_up_m, n_trees)], 1)  # (T, 3)
    clear = rng.uniform(*clear_m, n_trees)
    centres = feet + np.c_[np.zeros((n_trees, 2)), clear + radii[:, 2]]  # (T, 3) vertical trunks
    pts, tree, kind = [], [], []

    def inside(p: np.ndarray, t: int) -> np.ndarray:  # normalised ellipsoid radius of points p about tree t
        return np.linalg.norm((p - centres[t]) / radii[t], axis=1)

    for t in range(n_trees):
        a, b, c = radii[t]
        area = 4 * np.pi * ((a * b) ** 1.6 + (a * c) ** 1.6 + (b * c) ** 1.6) ** (1 / 1.6) / 3 ** (1 / 1.6)
        shell = centres[t] + _ellipsoid_shell(rng, int(points_per_m2 * area), radii[t], 0.08)
        n_in = int(interior_fraction * len(shell))
        d = rng.normal(size=(n_in, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        inner = centres[t] + d * radii[t] * rng.uniform(0, 1, (n_in, 1)) ** (1 / 3)
        own = np.vstack([shell, inner])
        r_own = inside(own, t)
        keep = np.ones(len(own), bool)
        for u in (t - 1, t + 1):
            if 0 <= u < n_trees:
                r_u = inside(own, u)
                # shell points inside the neighbour are hidden; interior points go to the nearer centre
                keep &= np.r_[r_u[: len(shell)] >= 1.0, r_u[len(shell):] >= r_own[len(shell):]]
        trunk_len = clear[t] + 0.3 * radii[t, 2]
        trunk = _cylinder(rng, int(points_per_m2 * 2 * np.pi * TRUNK_RADIUS_M * trunk_len), feet[t] - [0, 0, 0.05],
                          feet[t] + [0, 0, trunk_len], TRUNK_RADIUS_M)
        pts += [own[keep], trunk]
        tree += [np.full(int(keep.sum()) + len(trunk), t)]
        kind += [np.full(int(keep.sum()) + len(trunk), KIND_TREE)]
    for t in branch_over:
        if t + 1 >= n_trees:
            continue
        a, c = radii[t, 0], radii[t, 2]
        start = centres[t] + [0.3 * a, 0.0, 0.95 * c]
        nb = t + 1
        # the clump hangs over the neighbour's crown, a quarter of its radius in from its centre; raised
        # until the whole branch and clump keep BRANCH_GAP_M off the neighbour's ellipsoid
        end = np.array([centres[nb, 0] - 0.25 * radii[nb, 0], centres[t, 1], centres[nb, 2]])
        line = np.linspace(0, 1, 50)[:, None]
        for _ in range(100):  # at most 1 m up (a start near the neighbour never clears)
            path = start + line * (end - start)  # (50, 3)
            gap = (np.linalg.norm((path - centres[nb]) / radii[nb], axis=1) - 1.0) * radii[nb].min()
            clearance = np.minimum(gap[:-1], gap[-1] - 0.08)  # the clump (radius 8 cm) at the end
            if clearance.min() >= BRANCH_GAP_M:
                break
            end[2] += 0.01
        br = _cylinder(rng, int(points_per_m2 * 2 * np.pi * 0.02 * np.linalg.norm(end - start)), start, end, 0.02)
        clump = end + _ellipsoid_shell(rng, int(points_per_m2 * 4 * np.pi * 0.08**2), np.full(3, 0.08), 0.2)
        pts += [br, clump]
        tree += [np.full(len(br) + len(clump), t)]
        kind += [np.full(len(br) + len(clump), KIND_TREE)]
    # ground: the plane over the row's extent with weeds-free roughness
    x0, x1 = xs.min() - 1.0, xs.max() + 1.0
    ng = int(points_per_m2 * (x1 - x0) * 1.6 * 0.5)
    gx, gy = rng.uniform(x0, x1, ng), rng.uniform(-0.8, 0.8, ng)
    pts.append(np.stack([gx, gy, ground_z(gx, gy)], 1))
    tree.append(np.full(ng, -1))
    kind.append(np.full(ng, KIND_GROUND))
    post_feet = []
    for i in posts_between:
        px = 0.5 * (xs[i] + xs[i + 1])
        foot = np.array([px, 0.0, ground_z(px, 0.0)])
        post = _cylinder(rng, int(points_per_m2 * 2 * np.pi * POST_RADIUS_M * POST_HEIGHT_M), foot,
                         foot + [0, 0, POST_HEIGHT_M], POST_RADIUS_M)
        post_feet.append(foot)
        pts.append(post)
        tree.append(np.full(len(post), -1))
        kind.append(np.full(len(post), KIND_POST))
    if n_flying:
        t_f = rng.integers(0, n_trees, n_flying)
        fly = centres[t_f] + np.c_[rng.normal(0, 0.1, (n_flying, 2)), radii[t_f, 2] + rng.uniform(0.3, 1.0, n_flying)]
        pts.append(fly)
        tree.append(t_f)
        kind.append(np.full(n_flying, KIND_FLYING))
    p = np.vstack(pts)
    p = p + rng.normal(0, noise_m, p.shape)
    tree_a, kind_a = np.concatenate(tree), np.concatenate(kind)
    heights = np.array([np.max((p[(tree_a == t) & (kind_a == KIND_TREE)] - feet[t]) @ n) for t in range(n_trees)])
    return SyntheticRow(p, tree_a, kind_a, feet, feet.copy(), np.tile(n, (n_trees, 1)),
                        clear, heights, np.array(post_feet).reshape(-1, 3), POST_RADIUS_M)
