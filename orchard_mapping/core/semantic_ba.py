"""Semantic bundle adjustment of the two merged sides (paper: "Semantic Bundle Adjustment", eq. objectSBA).

The paper adds to the feature BA of both sides one cost per point of each semantic object: a trunk's
points must lie on one cylinder, a tree's ground points within one plane's band, whichever side saw
them. Here the same coupling is built from GTSAM's built-in factors on each side's fitted shapes
(a Python factor per point would cost seconds per iteration: docs/dependencies.md):

- each side's keyframe poses form a chain of BetweenFactorPose3 with the relative poses of that
  side's own bundle adjustment: the side may bend, as much as its drift allows (sigmas per step). Only
  the keyframes that measure something (and the chain's ends) are variables: the steps between two of
  them are one factor with their composed covariance, and the keyframes between are filled in after
  (the same optimum to first order; 0.3 k instead of 12 k poses on a 100-tree row);
- each tree paired across the sides is one trunk variable (Pose3 in map: origin on the axis at the
  diameter height, z along the axis). Each side measures it from one keyframe (the one whose view of
  the trunk had the most pixels) as a BetweenFactorPose3 camera -> trunk whose noise is free about the
  axis (a cylinder has no heading) and loose along it (where the diameter height falls depends on the
  ground), tight across it and in tilt: the two halves of a trunk must share one axis;
- each tree with a local ground on both sides is one OrientedPlane3 variable, measured from the same
  keyframes (OrientedPlane3Factor);
- each trellis post seen in two or more passes of a side (core/posts.py) is one Pose3 too, measured
  like a trunk from one keyframe per pass: it ties a side's raised sweep, which sees no trunk, to its
  level sweep (a 30-tree row: merged map 0.38 -> 0.04 deg);
- gauge: a prior on the first front keyframe (map = odom_front).

Levenberg-Marquardt with Huber-robust semantic factors. Frames: poses T_map_cam of the colour
optical frame, metres, radians inside GTSAM.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import gtsam
import numpy as np
from gtsam.symbol_shorthand import B, F, G, P, T
from scipy.spatial.transform import Rotation

from orchard_mapping.core.bundle_adjustment import optimise_in_steps
from orchard_mapping.errors import AlignmentError

__all__ = ["PostShape", "SemanticBAParams", "SideShapes", "SemanticBAResult", "TrunkShape", "semantic_bundle_adjust",
           "trunk_frame", "HeightAnchor"]

logger = logging.getLogger(__name__)

GAUGE_SIGMA = 1e-6  # rad and m: the first front keyframe is held
# m, along the axis for a side whose trunk has no local ground: on the 2-tree test row such a trunk's foot was
# 15 cm too high, and held at the grounded sigma it lifted the whole back side by 6 cm.
UNGROUNDED_ALONG_SIGMA_M = 0.5


@dataclass
class SemanticBAParams:
    """Settings of the semantic bundle adjustment (config section `semantic_ba`)."""

    __pydantic_config__ = {"extra": "forbid"}

    # Per keyframe step of a side's own chain. A side drifts 0.1-0.3 % of its path (benchmarks/
    # single_side.py): ~1 cm over 10 m, i.e. ~0.7 mm per 5 cm step as a random walk.
    step_sigma_rot_deg: float = 0.02
    step_sigma_trans_m: float = 0.001
    # A side's trunk: axis point across the axis, along it, axis tilt; heading is free. Along the axis the
    # trunk frame's origin sits at the diameter height above that side's own local ground, which under
    # weeds is centimetres off the other side's: held at 3 cm, the 10-tree slope_weeds row merged 0.202 deg
    # / 20.7 mm off (0.095 / 5.7 at 0.5 m; 0.10 m: 13.3 mm), standard 0.077 / 4.6 -> 0.076 / 3.7 mm. The
    # heights are left to the shared grounds (plane factors).
    trunk_sigma_across_m: float = 0.003
    # Across the axis in the viewing direction (across the row) a side's axis point is also where a circle
    # fitted to the half of the trunk that side sees puts the centre: on a trunk that is not round it sits
    # towards or away from that side's cameras by up to the difference of its semi-axes, the other side's
    # the opposite way (a trunk frame's x runs along the row, y across it). Held at 3 mm, a 10-tree row of
    # 3-10 % elliptical trunks merged 16.3 mm off (initial transform 8.5); at 8 mm 5.9 mm. Over ten rows
    # (round and elliptical, 10 and 30 trees) the merged map's error summed 73.0 mm at 3 mm, 65.9 at 8
    # (worst row 12.8 -> 9.1 mm; the 30-tree round row 6.9 -> 9.1): docs/merge.md.
    trunk_sigma_depth_m: float = 0.008
    trunk_sigma_along_m: float = 0.5
    trunk_sigma_tilt_deg: float = 0.5
    # A side's local ground: normal (deg) and offset (m).
    ground_sigma_normal_deg: float = 2.0
    ground_sigma_offset_m: float = 0.01
    huber_k: float = 1.345
    max_iterations: int = 50
    # Stop when an LM iteration lowers the error by less than this fraction. With the condensed chains the
    # 100 tiled trees take 21 iterations, 0.5 s (1e-5: 57, 1.2 s; error 43.4 vs 42.7); the simulated 30-
    # and 10-tree rows merge to within 0.5 mm and 0.001 deg of 1e-5's (merged map, trees, gaps).
    relative_error_tol: float = 1e-3
    # Trellis posts (core/posts.py): one keyframe per pass by a post measures it, as a trunk is measured
    # (heading free), from that frame's depth alone. They tie a side's raised sweep, which sees no trunk,
    # to its level sweep. One view's axis: 0.7 / 4 mm median off the truth (level / raised views,
    # standard row, exact masks), tilt 0.1 / 0.5 deg.
    use_posts: bool = True
    post_sigma_across_m: float = 0.005
    post_sigma_along_m: float = 0.5  # the two passes see different stretches of the post
    post_sigma_tilt_deg: float = 1.0
    # m: the back side's height held at the initial alignment's (HeightAnchor); 0 = not held. Without it a
    # row whose back side had no local ground merged 41 mm off (its trunks' wide grounds 5 cm off); held
    # at 2 / 5 / 10 cm: 2.8 / 11.1 / 26.2 mm, the nine other rows' sum 62.3 mm without, 63.1 at 2 cm.
    height_sigma_m: float = 0.02


@dataclass(frozen=True)
class TrunkShape:
    """One side's view of a tree: its trunk frame and local ground, from one keyframe."""

    tree: int  # the pair index: the same tree on both sides
    keyframe: int  # index into that side's poses
    T_cam_trunk: np.ndarray  # (4, 4) trunk frame (origin on the axis at the diameter height, z = axis, x along the row)
    ground_cam: np.ndarray | None = None  # (4,) plane n . p + d = 0 in that camera frame (n up), or None
    # The origin's height along the axis came from this side's local ground. Without one it is the lowest
    # trunk point (weeds may hide the foot): its height is then not a measurement (loose along the axis).
    grounded: bool = True


@dataclass(frozen=True)
class PostShape:
    """One pass's view of a trellis post: its frame in one keyframe's camera (origin on the axis at the
    post's reference point, shared by every view of that post; z along the axis)."""

    post: int  # the post's index: the same post in every view, either side
    keyframe: int  # index into that side's poses
    T_cam_post: np.ndarray  # (4, 4)


@dataclass(frozen=True)
class SideShapes:
    poses: np.ndarray  # (K, 4, 4) T_map_cam, initial (the back side already moved by the initial transform)
    trunks: list[TrunkShape]
    posts: list[PostShape] = field(default_factory=list)

    def trunk(self, tree: int) -> TrunkShape:
        """This side's view of `tree`."""
        return next(t for t in self.trunks if t.tree == tree)


@dataclass(frozen=True)
class SemanticBAResult:
    front_poses: np.ndarray  # (K_f, 4, 4) T_map_cam
    back_poses: np.ndarray  # (K_b, 4, 4)
    trunks_map: dict[int, np.ndarray]  # tree -> (4, 4) trunk frame in map
    gaps_before_mm: dict[int, float]  # tree -> distance between the two sides' axes at the diameter height
    gaps_after_mm: dict[int, float]
    error_initial: float
    error_final: float
    iterations: int


def trunk_frame(origin: np.ndarray, axis: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(4, 4) frame with the origin on the axis, z along it, x towards `ref` (3,) made perpendicular."""
    z = np.asarray(axis, float) / np.linalg.norm(axis)
    x = np.asarray(ref, float) - (np.asarray(ref, float) @ z) * z
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.cross(z, [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    M = np.eye(4)
    M[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    M[:3, 3] = origin
    return M


def _axis_gap_mm(Tf: np.ndarray, Tb: np.ndarray) -> float:
    """mm: the back trunk's axis point off the front trunk's axis line (both (4, 4) in map)."""
    z = Tf[:3, 2]
    d = Tb[:3, 3] - Tf[:3, 3]
    return float(1000 * np.linalg.norm(d - (d @ z) * z))


def _trunks_in_map(front: SideShapes, back: SideShapes, fp: np.ndarray, bp: np.ndarray) -> dict[int, float]:
    f = {t.tree: fp[t.keyframe] @ t.T_cam_trunk for t in front.trunks}
    b = {t.tree: bp[t.keyframe] @ t.T_cam_trunk for t in back.trunks}
    return {k: _axis_gap_mm(f[k], b[k]) for k in sorted(set(f) & set(b))}


def _skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices of v (..., 3)."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def chain_covariances(poses: np.ndarray, anchors: np.ndarray, q_rot: float, q_trans: float) -> np.ndarray:
    """(K, 6, 6) covariance, in GTSAM's Pose3 tangent (rotation, translation) at keyframe k, of the pose of k
    relative to the last anchor before it, reached through the chain of per-step BetweenFactorPose3 with
    variances q_rot (rad^2) and q_trans (m^2) per axis; poses (K, 4, 4), anchors sorted indices (0 among them).

    Step j's noise reaches k through Ad(T_{j+1,k}^-1) = [[R', 0], [t'^ R', R']] (R' = R_k^T R_{j+1},
    t' = R_k^T (p_{j+1} - p_k)): summed over the steps, [[m q_r I, -q_r [s]x], [q_r [s]x, q_r C + m q_t I]]
    with m steps, s = sum t' and C = sum (|t'|^2 I - t' t'^T), all from prefix sums of the positions."""
    K = len(poses)
    R, p = poses[:, :3, :3], poses[:, :3, 3]  # (K, 3, 3), (K, 3)
    a = anchors[np.maximum(np.searchsorted(anchors, np.arange(K)) - 1, 0)]  # (K,) the last anchor before k
    m = (np.arange(K) - a).astype(float)  # steps from it
    cs1 = np.cumsum(p, axis=0)  # (K, 3)
    cs2 = np.cumsum(p[:, :, None] * p[:, None, :], axis=0)  # (K, 3, 3)
    S1 = cs1 - cs1[a]  # (K, 3) sum of p_i, i = a+1 .. k
    S2 = cs2 - cs2[a]
    D = S1 - m[:, None] * p  # (K, 3) sum of (p_i - p_k)
    M = S2 - S1[:, :, None] * p[:, None, :] - p[:, :, None] * S1[:, None, :] + m[:, None, None] * p[:, :, None] * p[:, None, :]
    Rt = np.transpose(R, (0, 2, 1))
    s = np.einsum("kij,kj->ki", Rt, D)  # (K, 3) in k's frame
    C = np.trace(M, axis1=1, axis2=2)[:, None, None] * np.eye(3) - Rt @ M @ R  # (K, 3, 3)
    eye = np.eye(3)[None]
    cov = np.zeros((K, 6, 6))
    cov[:, :3, :3] = q_rot * m[:, None, None] * eye
    cov[:, :3, 3:] = -q_rot * _skew(s)
    cov[:, 3:, :3] = q_rot * _skew(s)
    cov[:, 3:, 3:] = q_rot * C + q_trans * m[:, None, None] * eye
    return cov


def fill_chain(poses: np.ndarray, anchors: np.ndarray, optimised: dict[int, np.ndarray], cov: np.ndarray) -> np.ndarray:
    """(K, 4, 4) every keyframe after the anchors were optimised: between anchors a < b, the chain's
    most likely poses given both ends (the Gaussian bridge of its steps): P_k' = P_a' T_ak Exp(e_k) with
    e_k = cov_k Ad(T_kb^-1)^T cov_b^-1 xi_b, xi_b = Log((P_a' T_ab)^-1 P_b'). Exactly what the whole chain
    in the factor graph would give, to first order in the corrections (sub-millimetre here)."""
    out = np.empty_like(poses)
    R, p = poses[:, :3, :3], poses[:, :3, 3]
    for i, b in enumerate(anchors):
        out[b] = optimised[int(b)]
        if i == 0:
            continue
        a = int(anchors[i - 1])
        ks = np.arange(a + 1, b)
        if not len(ks):
            continue
        T_ab = np.linalg.inv(poses[a]) @ poses[b]
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(np.linalg.inv(optimised[a] @ T_ab) @ optimised[int(b)]))  # (6,)
        w = np.linalg.solve(cov[b], xi)  # (6,)
        Rp = np.transpose(R[b])[None] @ R[ks]  # (n, 3, 3) R' = R_b^T R_k
        tp = (p[ks] - p[b]) @ R[b]  # (n, 3) t' = R_b^T (p_k - p_b)
        # Ad(T_kb^-1)^T w = (R'^T (w_r - t' x w_t), R'^T w_t)
        RpT = np.transpose(Rp, (0, 2, 1))
        g = np.concatenate([np.einsum("kij,kj->ki", RpT, w[:3] - np.cross(tp, w[3:])),
                            np.einsum("kij,j->ki", RpT, w[3:])], axis=1)  # (n, 6)
        e = np.einsum("kij,kj->ki", cov[ks], g)  # (n, 6)
        T_ak = np.linalg.inv(poses[a])[None] @ poses[ks]  # (n, 4, 4)
        step = np.tile(np.eye(4), (len(ks), 1, 1))
        step[:, :3, :3] = Rotation.from_rotvec(e[:, :3]).as_matrix()
        step[:, :3, 3] = e[:, 3:]  # first order in the (sub-mm, sub-millidegree) correction
        out[ks] = optimised[a][None] @ T_ak @ step
    return out


@dataclass(frozen=True)
class HeightAnchor:
    """How high the back side sits, from the initial alignment (the two sides' whole ground planes): the
    back side's point `point` (3,) m in map at its initial poses belongs at `height` m along `up` (3,) unit,
    within `sigma_m`. Trunks say almost nothing along their axes (each side's diameter height hangs on its
    own ground, loose), and shared grounds exist only where both sides fitted a local ground: on a row
    whose back side had none (a 10-tree standard row, elliptical trunks, seed 1) the trunks alone lowered
    the back side by 55 mm, onto its wide grounds' heights."""

    up: np.ndarray
    point: np.ndarray
    height: float
    sigma_m: float


def _add_height_anchor(graph: gtsam.NonlinearFactorGraph, k: int, T_map_cam: np.ndarray, anchor: HeightAnchor
                       ) -> None:
    """The anchor as a built-in PriorFactorPose3 on back keyframe k whose information holds only the
    anchor point's height: for X = M Exp([w; v]) the point p (camera frame) rises by u.v - (u x p).w, u the
    up direction in the camera (first order; the corrections are centimetres)."""
    p = (np.linalg.inv(T_map_cam) @ np.append(anchor.point, 1.0))[:3]
    u = T_map_cam[:3, :3].T @ anchor.up
    a = np.concatenate([-np.cross(u, p), u])  # (6,) rotation first, as gtsam's Pose3 tangent
    info = np.outer(a, a) / anchor.sigma_m ** 2 + 1e-9 * np.eye(6)  # rank one; the rest free
    M = T_map_cam.copy()
    M[:3, 3] += anchor.up * (anchor.height - float(anchor.up @ anchor.point))  # the pose that puts it there
    graph.add(gtsam.PriorFactorPose3(B(k), gtsam.Pose3(M), gtsam.noiseModel.Gaussian.Information(info)))


def semantic_bundle_adjust(front: SideShapes, back: SideShapes, params: SemanticBAParams,
                           height: HeightAnchor | None = None) -> SemanticBAResult:
    """Both sides' keyframe poses and the shared trunks and grounds (module docstring); `height` holds the back
    side's height where the grounds do not."""
    shared = {t.tree for t in front.trunks} & {t.tree for t in back.trunks}
    if len(shared) < 2:
        raise AlignmentError(f"semantic BA needs at least two trees seen from both sides, got {len(shared)}")
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    huber = gtsam.noiseModel.mEstimator.Huber.Create(params.huber_k)
    def trunk_noise(along_m: float) -> gtsam.noiseModel.Base:
        return gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Diagonal.Sigmas(np.array(
            [np.radians(params.trunk_sigma_tilt_deg)] * 2 + [10.0]  # rotation: tilt x, y; heading free
            + [params.trunk_sigma_across_m, params.trunk_sigma_depth_m, along_m])))

    grounded_noise, loose_noise = trunk_noise(params.trunk_sigma_along_m), trunk_noise(UNGROUNDED_ALONG_SIGMA_M)
    # OrientedPlane3Factor takes a Gaussian model only: a pair of grounds that disagree by more than 3
    # sigmas at the initial poses (weeds taken for ground on one side) is left out instead.
    plane_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(
        [np.radians(params.ground_sigma_normal_deg)] * 2 + [params.ground_sigma_offset_m]))
    # Each side's chain between the keyframes that measure something (trunks, grounds, posts; and its ends)
    # is one BetweenFactorPose3 with the covariance of its steps composed: the same optimum as one factor
    # per step, to first order, with 0.3k instead of 12k poses on a 100-tree row (LM took 4.4 s there,
    # 4.4x the 30-tree time); the keyframes between are filled in afterwards (fill_chain).
    q_rot, q_trans = np.radians(params.step_sigma_rot_deg) ** 2, params.step_sigma_trans_m ** 2
    chains = {}
    k_height = None
    if height is not None:  # the back keyframe nearest the anchor point carries it
        k_height = int(np.argmin(np.linalg.norm(back.poses[:, :3, 3] - height.point, axis=1)))
    for sym, side in ((F, front), (B, back)):
        used = ({t.keyframe for t in side.trunks if t.tree in shared}
                | ({p.keyframe for p in side.posts} if params.use_posts else set())
                | ({k_height} if sym is B and k_height is not None else set()))
        anchors = np.array(sorted(used | {0, len(side.poses) - 1}), np.int64)
        cov = chain_covariances(side.poses, anchors, q_rot, q_trans)
        chains[sym] = (anchors, cov)
        for k in anchors:
            values.insert(sym(int(k)), gtsam.Pose3(side.poses[k]))
        for a, b in zip(anchors[:-1], anchors[1:], strict=True):
            rel = gtsam.Pose3(np.linalg.inv(side.poses[a]) @ side.poses[b])
            graph.add(gtsam.BetweenFactorPose3(sym(int(a)), sym(int(b)), rel,
                                               gtsam.noiseModel.Gaussian.Covariance(cov[b])))
    graph.add(gtsam.PriorFactorPose3(F(0), gtsam.Pose3(front.poses[0]),
                                     gtsam.noiseModel.Isotropic.Sigma(6, GAUGE_SIGMA)))
    if height is not None:
        _add_height_anchor(graph, k_height, back.poses[k_height], height)
    grounds: set[int] = set()
    front_map = {t.tree: front.poses[t.keyframe] @ t.T_cam_trunk for t in front.trunks if t.tree in shared}
    for tree, M in front_map.items():  # initial: the front side's trunk
        values.insert(T(tree), gtsam.Pose3(M))
    for sym, side in ((F, front), (B, back)):
        for t in side.trunks:
            if t.tree not in shared:
                continue
            graph.add(gtsam.BetweenFactorPose3(sym(t.keyframe), T(t.tree), gtsam.Pose3(t.T_cam_trunk),
                                               grounded_noise if t.grounded else loose_noise))
    for t in front.trunks:
        other = back.trunk(t.tree) if t.tree in shared else None
        if t.ground_cam is None or other is None or other.ground_cam is None:
            continue
        n_f, d_f = _plane_in_map(t.ground_cam, front.poses[t.keyframe])
        n_b, d_b = _plane_in_map(other.ground_cam, back.poses[other.keyframe])
        x = front_map[t.tree][:3, 3]  # the trunk: where the two planes are compared
        if (np.degrees(np.arccos(np.clip(n_f @ n_b, -1, 1))) > 3 * params.ground_sigma_normal_deg
                or abs((n_b @ x + d_b) - (n_f @ x + d_f)) > 3 * params.ground_sigma_offset_m):
            continue
        values.insert(G(t.tree), gtsam.OrientedPlane3(*n_f, d_f))
        graph.add(gtsam.OrientedPlane3Factor(np.asarray(t.ground_cam, float), plane_noise, F(t.keyframe), G(t.tree)))
        graph.add(gtsam.OrientedPlane3Factor(np.asarray(other.ground_cam, float), plane_noise, B(other.keyframe),
                                             G(t.tree)))
        grounds.add(t.tree)
    n_posts = _add_posts(graph, values, front, back, params, huber) if params.use_posts else 0
    before = _trunks_in_map(front, back, front.poses, back.poses)
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(params.max_iterations)
    lm.setRelativeErrorTol(params.relative_error_tol)
    opt = gtsam.LevenbergMarquardtOptimizer(graph, values, lm)
    e0 = graph.error(values)
    result = optimise_in_steps(opt, lm)
    e1 = graph.error(result)
    fp, bp = (fill_chain(side.poses, chains[sym][0], {int(k): result.atPose3(sym(int(k))).matrix()
                                                        for k in chains[sym][0]}, chains[sym][1])
              for sym, side in ((F, front), (B, back)))
    after = _trunks_in_map(front, back, fp, bp)
    logger.info("semantic BA: %d + %d keyframes, %d trunks, %d grounds, %d posts; error %.1f -> %.1f in %d "
                "iterations; trunk axis gap median %.1f -> %.1f mm", len(fp), len(bp), len(shared), len(grounds),
                n_posts, e0, e1,
                opt.iterations(), np.median(list(before.values())), np.median(list(after.values())))
    return SemanticBAResult(fp, bp, {k: result.atPose3(T(k)).matrix() for k in sorted(shared)}, before, after,
                            float(e0), float(e1), int(opt.iterations()))


def _plane_in_map(plane_cam: np.ndarray, T_map_cam: np.ndarray) -> tuple[np.ndarray, float]:
    """(n (3,), d) of n . p + d = 0 in map, from the plane (4,) in the camera frame."""
    R, t = T_map_cam[:3, :3], T_map_cam[:3, 3]
    n = R @ plane_cam[:3]
    return n, float(plane_cam[3] - n @ t)


def _add_posts(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, front: SideShapes, back: SideShapes,
               params: SemanticBAParams, huber: gtsam.noiseModel.mEstimator.Huber) -> int:
    """One Pose3 per post seen in two or more passes (either side), measured from each pass's keyframe
    like a trunk (heading free, loose along the axis). Returns the number of posts added."""
    noise = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Diagonal.Sigmas(np.array(
        [np.radians(params.post_sigma_tilt_deg)] * 2 + [10.0]
        + [params.post_sigma_across_m] * 2 + [params.post_sigma_along_m])))
    views: dict[int, list[tuple[object, SideShapes, PostShape]]] = {}
    for sym, side in ((F, front), (B, back)):
        for p in side.posts:
            views.setdefault(p.post, []).append((sym, side, p))
    n = 0
    for post, vs in sorted(views.items()):
        if len(vs) < 2:
            continue
        sym, side, p = vs[0]
        values.insert(P(post), gtsam.Pose3(side.poses[p.keyframe] @ p.T_cam_post))
        for sym, _side, p in vs:
            graph.add(gtsam.BetweenFactorPose3(sym(p.keyframe), P(post), gtsam.Pose3(p.T_cam_post), noise))
        n += 1
    return n
