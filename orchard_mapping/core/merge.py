"""Initial transform between the two sides from paired trunks and local grounds (paper: "Merging
Two-Sides 3D Reconstruction", "Initial Transformation").

Each trunk seen from both sides gives its axis n_d and a point O_d on it in both frames; each tree's
local ground gives its normal n_p and a point O_p. The rigid transform [R | t] odom_front <- odom_back
must satisfy, for every pair (the paper's constraints 1-3):

  1. R n_d^B = n_d^F and R n_p^B = n_p^F (axes and normals agree);
  2. n_d^F x (R O_d^B + t - O_d^F) = 0 (the back origin lies on the front axis);
  3. n_p^F . (R O_p^B + t - O_p^F) = 0 (the back origin lies on the front plane).

They are linear in the 12 entries of [R | t]: stacked into A x = b and solved by least squares, R is
replaced by the nearest rotation (SVD, Frobenius norm), then the same residuals are minimised with a
Huber loss over a rotation vector (Rodrigues) and t by Levenberg-Marquardt. Residuals are scaled by
their sigmas, so one pair on a weed ramp or a leaning post is down-weighted and reported.

Frames: each side's odom frame; metres, unit vectors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from orchard_mapping.core.geometry import make_transform
from orchard_mapping.errors import AlignmentError

__all__ = ["HeightPrior", "MergeParams", "PairResidual", "SemanticPair", "InitialTransform", "initial_transform"]


@dataclass
class MergeParams:
    """Settings of the initial transform (config section `merge`)."""

    __pydantic_config__ = {"extra": "forbid"}

    # "semantic_ba": initial alignment, initial transform, then semantic bundle adjustment; "initial":
    # without the bundle adjustment; "icp": the point-to-plane ICP baseline; "off": each side on its own.
    method: str = "semantic_ba"
    # Sigmas of the constraint residuals: a trunk's whole-length axis is good to ~0.5 deg and its line
    # to a few millimetres; a local ground's normal to ~1 deg and its height to ~1 cm (benchmarks/trunks.py).
    sigma_axis_rad: float = 0.01
    sigma_line_m: float = 0.005
    sigma_normal_rad: float = 0.02
    sigma_plane_m: float = 0.01
    # rad, tilt error of a local ground seen away from its trunk (normal errors median 1-4 deg on the
    # 10-tree rows): its height at the trunk gets sigma_plane_m (+) this times support_offset_m.
    ground_tilt_sigma_rad: float = 0.05
    # m, the initial alignment's height of the back side (front-view boundaries and grounds): 8, 17 and
    # 2 mm off on the 2-tree test row and the 10-tree standard and slope_weeds rows. 0 = not used.
    sigma_alignment_height_m: float = 0.02
    huber_k: float = 1.345  # in sigmas

    def __post_init__(self) -> None:
        if self.method not in ("semantic_ba", "initial", "icp", "off"):
            raise ValueError(f"merge.method must be 'semantic_ba', 'initial', 'icp' or 'off', got {self.method!r}")
        for name in ("sigma_axis_rad", "sigma_line_m", "sigma_normal_rad", "sigma_plane_m", "huber_k",
                     "ground_tilt_sigma_rad"):
            if not getattr(self, name) > 0:
                raise ValueError(f"merge.{name} must be > 0, got {getattr(self, name)!r}")
        if not self.sigma_alignment_height_m >= 0:
            raise ValueError(f"merge.sigma_alignment_height_m must be >= 0, got {self.sigma_alignment_height_m!r}")


@dataclass(frozen=True)
class SemanticPair:
    """One tree seen from both sides: its trunk axis and (when fitted on both) its local ground."""

    front_id: int
    back_id: int
    axis_f: np.ndarray  # (3,) unit, odom_front
    origin_f: np.ndarray  # (3,) m, a point on the front axis
    axis_b: np.ndarray  # (3,) unit, odom_back
    origin_b: np.ndarray  # (3,) m
    ground_f: tuple[np.ndarray, np.ndarray] | None = None  # (normal (3,), point (3,)) odom_front
    ground_b: tuple[np.ndarray, np.ndarray] | None = None
    # m, how far from the trunk each ground was seen (LocalGroundFit.support_offset_m; 0 = at the trunk)
    ground_reach_m: tuple[float, float] = (0.0, 0.0)

    def plane_sigma_m(self, mp: "MergeParams") -> float:
        """m, sigma of this pair's ground height at the trunk: the base sigma plus each plane's tilt error
        carried over the distance from where it was seen."""
        reach = np.nan_to_num(np.asarray(self.ground_reach_m, float))
        return float(np.sqrt(mp.sigma_plane_m**2 + mp.ground_tilt_sigma_rad**2 * float(reach @ reach)))


@dataclass(frozen=True)
class HeightPrior:
    """The initial alignment's say on how high the back side sits: the back point `point_b` (odom_back)
    belongs at the height of `target_f` (odom_front) along `up` (odom_front, unit). Trunk lines say
    nothing along the axis; only grounds do, and a tree's local ground seen in a corner of its disk can
    be centimetres off at the trunk (2-tree test row: one such ground put the back side 35-49 mm low;
    the alignment's height, from the front-view boundaries, was 8 mm off)."""

    up: np.ndarray  # (3,)
    point_b: np.ndarray  # (3,) m
    target_f: np.ndarray  # (3,) m


@dataclass(frozen=True)
class PairResidual:
    front_id: int
    back_id: int
    axis_deg: float  # angle between the axes after the transform
    line_mm: float  # distance of the back origin from the front axis
    ground_deg: float | None  # angle between the ground normals
    ground_mm: float | None  # distance of the back ground point from the front plane


@dataclass(frozen=True)
class InitialTransform:
    T_front_back: np.ndarray  # (4, 4) rigid odom_front <- odom_back
    residuals: tuple[PairResidual, ...]
    linear_T: np.ndarray  # (4, 4) the least-squares solution with its nearest rotation (before LM)
    cost_initial: float  # Huber cost at the linear solution
    cost_final: float


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _linear_system(pairs: list[SemanticPair], prior: HeightPrior | None, mp: MergeParams
                   ) -> tuple[np.ndarray, np.ndarray]:
    """A (rows, 12), b (rows,) of constraints 1-3 with x = [r1; r2; r3; t] (R's columns, then t); the
    height prior's row weighted against the ground rows by their sigmas."""
    rows, rhs = [], []

    def rotate_rows(v_b: np.ndarray, v_f: np.ndarray) -> None:  # R v_b = v_f
        for k in range(3):
            a = np.zeros(12)
            a[[k, 3 + k, 6 + k]] = v_b
            rows.append(a)
            rhs.append(v_f[k])

    for p in pairs:
        rotate_rows(p.axis_b, p.axis_f)
        if p.ground_f is not None and p.ground_b is not None:
            rotate_rows(p.ground_b[0], p.ground_f[0])
    for p in pairs:  # n_f x (R O_b + t) = n_f x O_f
        K = _skew(p.axis_f)
        a = np.hstack([p.origin_b[0] * K, p.origin_b[1] * K, p.origin_b[2] * K, K])  # (3, 12)
        rows.extend(a)
        rhs.extend(np.cross(p.axis_f, p.origin_f))
    for p in pairs:  # n_f . (R O_b + t) = n_f . O_f
        if p.ground_f is None or p.ground_b is None:
            continue
        n, o_b = p.ground_f[0], p.ground_b[1]
        w = mp.sigma_plane_m / p.plane_sigma_m(mp)
        rows.append(w * np.concatenate([o_b[0] * n, o_b[1] * n, o_b[2] * n, n]))
        rhs.append(w * float(n @ p.ground_f[1]))
    if prior is not None:  # up . (R c_b + t) = up . target
        w = mp.sigma_plane_m / mp.sigma_alignment_height_m
        u, c = prior.up, prior.point_b
        rows.append(w * np.concatenate([c[0] * u, c[1] * u, c[2] * u, u]))
        rhs.append(w * float(u @ prior.target_f))
    return np.asarray(rows), np.asarray(rhs)


def _residuals(R: np.ndarray, t: np.ndarray, A: "_PairArrays", mp: MergeParams,
               prior: HeightPrior | None = None) -> np.ndarray:
    """Sigma-scaled residuals of constraints 1-3: every pair's axis (3) and line (3), then the grounds'
    normal (3) and plane (1) of the pairs with grounds, then the height prior's one. Vectorised over the
    pairs (LM evaluates this a few hundred times: a loop over 100 pairs took 1.4 s of a 100-tree merge)."""
    out = [((A.axis_b @ R.T - A.axis_f) / mp.sigma_axis_rad).ravel(),
           (np.cross(A.axis_f, A.origin_b @ R.T + t - A.origin_f) / mp.sigma_line_m).ravel()]
    if len(A.g_nf):
        out.append(((A.g_nb @ R.T - A.g_nf) / mp.sigma_normal_rad).ravel())
        out.append(np.einsum("ij,ij->i", A.g_nf, A.g_pb @ R.T + t - A.g_pf) / A.g_sigma)
    if prior is not None:
        out.append(np.atleast_1d(prior.up @ (R @ prior.point_b + t - prior.target_f)) / mp.sigma_alignment_height_m)
    return np.concatenate(out)


@dataclass(frozen=True)
class _PairArrays:
    """The pairs' vectors stacked (P, 3), once per initial transform."""

    axis_f: np.ndarray
    axis_b: np.ndarray
    origin_f: np.ndarray
    origin_b: np.ndarray
    g_nf: np.ndarray  # (G, 3) the pairs with grounds on both sides
    g_nb: np.ndarray
    g_pf: np.ndarray
    g_pb: np.ndarray
    g_sigma: np.ndarray  # (G,) m, SemanticPair.plane_sigma_m

    @classmethod
    def of(cls, pairs: list[SemanticPair], mp: MergeParams) -> "_PairArrays":
        g = [p for p in pairs if p.ground_f is not None and p.ground_b is not None]

        def stack(vs: list[np.ndarray]) -> np.ndarray:
            return np.asarray(vs, float).reshape(-1, 3)

        return cls(stack([p.axis_f for p in pairs]), stack([p.axis_b for p in pairs]),
                   stack([p.origin_f for p in pairs]), stack([p.origin_b for p in pairs]),
                   stack([p.ground_f[0] for p in g]), stack([p.ground_b[0] for p in g]),
                   stack([p.ground_f[1] for p in g]), stack([p.ground_b[1] for p in g]),
                   np.array([p.plane_sigma_m(mp) for p in g], float))


def _huber_cost(r: np.ndarray, k: float) -> float:
    a = np.abs(r)
    return float(np.sum(np.where(a <= k, 0.5 * a**2, k * (a - 0.5 * k))))


def initial_transform(pairs: list[SemanticPair], params: MergeParams,
                      height_prior: HeightPrior | None = None) -> InitialTransform:
    """Rigid odom_front <- odom_back from paired trunk axes and local grounds (module docstring), with
    the initial alignment's height of the back side as a weak prior when given."""
    if len(pairs) < 2:
        raise AlignmentError(f"the initial transform needs at least two trunks seen from both sides, "
                             f"got {len(pairs)}")
    if height_prior is None and not any(p.ground_f is not None and p.ground_b is not None for p in pairs):
        raise AlignmentError("the initial transform needs at least one tree with a local ground on both sides "
                             "or the initial alignment's height")
    A, b = _linear_system(pairs, height_prior, params)
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    M = x[:9].reshape(3, 3).T  # columns r1 r2 r3
    U, _, Vt = np.linalg.svd(M)
    R0 = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    t0 = x[9:]
    # With R fixed at its nearest rotation, t again by least squares on the translation columns.
    resid_b = b - A[:, :9] @ R0.T.reshape(-1)
    t0, *_ = np.linalg.lstsq(A[:, 9:], resid_b, rcond=None)
    arrays = _PairArrays.of(pairs, params)
    cost0 = _huber_cost(_residuals(R0, t0, arrays, params, height_prior), params.huber_k)

    def fun(z: np.ndarray) -> np.ndarray:
        return _residuals(Rotation.from_rotvec(z[:3]).as_matrix() @ R0, z[3:], arrays, params, height_prior)

    sol = least_squares(fun, np.concatenate([np.zeros(3), t0]), loss="huber", f_scale=params.huber_k,
                        method="trf", x_scale=[0.01, 0.01, 0.01, 0.01, 0.01, 0.01])
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0
    t = sol.x[3:]
    res = []
    for p in pairs:
        a = float(np.degrees(np.arccos(np.clip((R @ p.axis_b) @ p.axis_f, -1.0, 1.0))))
        line = float(np.linalg.norm(np.cross(p.axis_f, R @ p.origin_b + t - p.origin_f)))
        gd = gm = None
        if p.ground_f is not None and p.ground_b is not None:
            gd = float(np.degrees(np.arccos(np.clip((R @ p.ground_b[0]) @ p.ground_f[0], -1.0, 1.0))))
            gm = float(1000 * abs(p.ground_f[0] @ (R @ p.ground_b[1] + t - p.ground_f[1])))
        res.append(PairResidual(p.front_id, p.back_id, a, 1000 * line, gd, gm))
    return InitialTransform(make_transform(R, t), tuple(res), make_transform(R0, t0), cost0,
                            _huber_cost(_residuals(R, t, arrays, params, height_prior), params.huber_k))
