"""Small pure geometry helpers: rotations, poses, similarity alignment, path length.

Conventions: quaternions are `qx qy qz qw` (scalar last, as TUM and ROS store
them); 4x4 transforms `T_a_b` map points in frame b to frame a
(p_a = T_a_b p_b); a similarity carries `s R` in its 3x3 block.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from orchard_mapping.errors import AlignmentError

__all__ = [
    "keyframes_every",
    "group_medians",
    "Similarity",
    "decompose_similarity",
    "make_transform",
    "matrix_to_quat",
    "path_length",
    "pose_matrices",
    "quat_to_matrix",
    "SlabIndex",
    "rotation_angle_deg",
    "transform_points",
    "umeyama",
]


def group_medians(groups: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(G,) the distinct ints of groups (N,) sorted, and (G,) the median of values (N,) in each: one sort
    for all of them (np.median group by group, an image's rows one at a time, was most of its caller's time)."""
    keys, counts = np.unique(groups, return_counts=True)
    order = np.lexsort((values, groups))
    vs, gs = values[order], groups[order]  # grouped, sorted within each group
    starts = np.searchsorted(gs, keys)
    return keys, 0.5 * (vs[starts + (counts - 1) // 2] + vs[starts + counts // 2])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions qx qy qz qw (normalised here) -> (..., 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=float)
    flat = q.reshape(-1, 4)
    norms = np.linalg.norm(flat, axis=1)
    if np.any(norms < 1e-12) or not np.all(np.isfinite(norms)):
        raise ValueError("quaternion with zero or non-finite norm")
    return Rotation.from_quat(flat / norms[:, None]).as_matrix().reshape(q.shape[:-1] + (3, 3))


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions qx qy qz qw with qw >= 0."""
    R = np.asarray(R, dtype=float)
    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()  # (N, 4)
    q = np.where(q[:, 3:4] < 0.0, -q, q)
    return q.reshape(R.shape[:-2] + (4,))


def make_transform(R: np.ndarray, t: np.ndarray, s: float = 1.0) -> np.ndarray:
    """4x4 similarity [[s R, t], [0, 1]] from R (3, 3), t (3,) m and scale s."""
    T = np.eye(4)
    T[:3, :3] = s * np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def pose_matrices(positions: np.ndarray, quaternions: np.ndarray) -> np.ndarray:
    """(N, 3) m and (N, 4) qx qy qz qw -> (N, 4, 4) poses."""
    positions = np.asarray(positions, dtype=float)
    T = np.tile(np.eye(4), (positions.shape[0], 1, 1))  # (N, 4, 4)
    T[:, :3, :3] = quat_to_matrix(quaternions)
    T[:, :3, 3] = positions
    return T


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform (rigid or similarity) to (N, 3) points."""
    T = np.asarray(T, dtype=float)
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    return points @ T[:3, :3].T + T[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix (3, 3) in degrees, in [0, 180]."""
    R = np.asarray(R, dtype=float)
    c = (np.trace(R) - 1.0) / 2.0
    # arccos is ill-conditioned near 0: use the skew part as well.
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.degrees(np.arctan2(s, np.clip(c, -1.0, 1.0))))


@dataclass(frozen=True)
class Similarity:
    """p_dst = s R p_src + t."""

    R: np.ndarray  # (3, 3) rotation
    t: np.ndarray  # (3,) m
    s: float = 1.0  # scale, 1 for a rigid transform

    def matrix(self) -> np.ndarray:  # (4, 4)
        return make_transform(self.R, self.t, self.s)


def decompose_similarity(T: np.ndarray) -> Similarity:
    """Split a 4x4 similarity into scale, nearest rotation and translation.

    s = cbrt(det(A)) of the 3x3 block A; R = the rotation nearest A / s (SVD).
    Raises ValueError if A is singular or reflects.
    """
    T = np.asarray(T, dtype=float)
    A = T[:3, :3]
    det = float(np.linalg.det(A))
    if not np.isfinite(det) or det <= 1e-12:
        raise ValueError(f"3x3 block is singular or a reflection (det = {det:.3g})")
    s = det ** (1.0 / 3.0)
    U, _, Vt = np.linalg.svd(A / s)
    R = U @ Vt
    return Similarity(R=R, t=T[:3, 3].copy(), s=s)


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> Similarity:
    """Least-squares similarity (Umeyama 1991) with dst ~ s R src + t.

    src, dst: (N, 3) corresponding points, N >= 3. Without scale it is the
    Kabsch solution (s = 1). Raises AlignmentError if too few points or the
    source points coincide.
    """
    src = np.asarray(src, dtype=float)
    dst = np.asarray(dst, dtype=float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise AlignmentError(f"point sets must both be (N, 3), got {src.shape} and {dst.shape}")
    n = src.shape[0]
    if n < 3:
        raise AlignmentError(f"alignment needs at least 3 corresponding points, got {n}")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    xs, xd = src - mu_s, dst - mu_d  # (N, 3)
    var_s = float(np.sum(xs**2) / n)
    if var_s < 1e-18:
        raise AlignmentError("source points coincide: alignment is undetermined")
    cov = xd.T @ xs / n  # (3, 3)
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    s = float(np.sum(D * np.diag(S)) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return Similarity(R=R, t=t, s=s)


def path_length(positions: np.ndarray) -> float:
    """Sum of distances between consecutive (N, 3) positions (m); 0 for N < 2."""
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    if positions.shape[0] < 2:
        return 0.0
    return float(np.linalg.norm(np.diff(positions, axis=0), axis=1).sum())


def keyframes_every(poses: np.ndarray, every_m: float) -> list[int]:
    """Indices of the camera poses (K, 4, 4) at least every_m (m) of straight-line distance on from the last one
    picked, the first included: the keyframes a detector is given along a side."""
    picks: list[int] = []
    last = None
    for k, T in enumerate(poses):
        if last is None or np.linalg.norm(T[:3, 3] - last) >= every_m - 1e-6:
            picks.append(k)
            last = T[:3, 3]
    return picks


def move_with_keyframes(points: np.ndarray, poses_before: np.ndarray, poses_after: np.ndarray) -> np.ndarray:
    """(P, 3) points of a side's cloud carried along with its keyframes: each point moves as the
    keyframe whose camera is nearest moved (T_after T_before^-1). The semantic BA bends a side, so one
    rigid transform would leave its far end off by the drift it corrected; corrections change slowly
    along a side (per-step sigmas), so the nearest camera is a good enough carrier.

    points (P, 3) in the frame of poses_before (K, 4, 4); poses_after (K, 4, 4) in the target frame."""
    from scipy.spatial import cKDTree

    pts = np.asarray(points, float)
    if len(pts) == 0:
        return pts.reshape(0, 3)
    delta = poses_after @ np.linalg.inv(poses_before)  # (K, 4, 4)
    _, k = cKDTree(poses_before[:, :3, 3]).query(pts, workers=-1)  # (P,) nearest keyframe camera
    # one product per keyframe on its points (a cloud has ~40 k points per metre, a side ~25 keyframes
    # per metre): a third faster than gathering a (P, 3, 3) rotation per point, and no such array
    order = np.argsort(k, kind="stable")
    starts = np.searchsorted(k[order], np.arange(len(delta) + 1))  # (K + 1,)
    out = np.empty_like(pts)
    for j in np.flatnonzero(np.diff(starts)):
        idx = order[starts[j]:starts[j + 1]]
        out[idx] = pts[idx] @ delta[j, :3, :3].T + delta[j, :3, 3]
    return out


class SlabIndex:
    """Indices of a cloud's points (P, 3) near a place, in the cloud's own order: the cloud is sorted once
    along its longest axis (a row's length), so a query reads a slab of the row rather than every point.
    Per tree over a whole row's cloud, reading every point made trunk modelling and the merge's tree feet
    grow with the square of the row's length (100-tree row: 8.5x the 30-tree row's time)."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = np.asarray(points)
        self.axis = int(np.argmax(np.ptp(self.points, axis=0))) if len(self.points) else 0
        self.order = np.argsort(self.points[:, self.axis], kind="stable")  # (P,)
        self.key = self.points[self.order, self.axis]  # (P,) sorted

    def slab(self, centre: np.ndarray, half: float) -> np.ndarray:
        """(n,) sorted indices of the points within half (m) of centre (3,) along the longest axis."""
        lo, hi = np.searchsorted(self.key, [centre[self.axis] - half, centre[self.axis] + half])
        return np.sort(self.order[lo:hi])

    def within_cube(self, centre: np.ndarray, half: float) -> np.ndarray:
        """(n, 3) the points strictly within the cube of half side `half` (m) around centre (3,)."""
        idx = self.slab(centre, half)
        return self.points[idx[np.all(np.abs(self.points[idx] - centre) < half, axis=1)]]


def checked_unit(v: np.ndarray, what: str, error: type[Exception] = ValueError) -> np.ndarray:
    """(3,) v scaled to unit length; `error` naming `what` if v is not a finite, non-zero 3-vector."""
    v = np.asarray(v, float).reshape(3)
    n = float(np.linalg.norm(v))
    if not n > 0 or not np.isfinite(n):
        raise error(f"{what} must be a finite non-zero 3-vector, got {v.tolist()}")
    return v / n
