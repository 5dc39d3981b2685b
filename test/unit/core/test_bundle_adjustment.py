"""Back end of single-side reconstruction on a synthetic orchard side.

The side: a camera moving sideways along x (10 cm between keyframes, about
0.5 m/s at 5 Hz) looking at a row 1.25 m away (z forward), landmarks spread
over 0.2-5 m depth plus a background at 6-10 m. Observations carry 0.5 px
pixel noise and 0.004 z^2 m depth noise; depth is missing for 10 % of them
and beyond 6 m. Initial poses carry a planted drift (1 % scale, 0.5 deg yaw
per 10 m, small random steps); initial landmarks back-project the first
observation with depth through the drifted poses, as a front end would.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orchard_mapping.core.bundle_adjustment import (
    BAResult,
    ReconstructionError,
    bundle_adjust,
    bundle_adjust_windowed,
    default_disparity_sigma,
    disparity_residual_sd,
    optimise_pose_graph,
)
from orchard_mapping.core.geometry import path_length, umeyama
from orchard_mapping.core.sidemap import LoopClosure, Observations
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import OrchardMappingError

INTR = CameraIntrinsics(width=640, height=480, fx=615.0, fy=615.0, cx=320.0, cy=240.0)


@dataclass(frozen=True)
class Side:
    truth: np.ndarray  # (K, 4, 4) true T_odom_cam
    drifted: np.ndarray  # (K, 4, 4) initial estimate
    points: np.ndarray  # (L, 3) true landmarks
    init_points: np.ndarray  # (L, 3) initial landmarks (NaN: no depth anywhere)
    obs: Observations
    outlier: np.ndarray  # (M,) bool, planted outliers


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _drift(truth: np.ndarray, rng: np.random.Generator, *, scale=1.01, yaw_deg_per_m=0.05,
           step_rot_deg=0.02, step_trans_m=0.001) -> np.ndarray:
    """Re-chain the true relative poses with a scale error, a yaw bias (about the camera's
    vertical y axis) and random steps: a front end's odometry drift."""
    out = [truth[0].copy()]
    for k in range(1, len(truth)):
        rel = np.linalg.inv(truth[k - 1]) @ truth[k]
        step = np.linalg.norm(rel[:3, 3])
        bias = Rotation.from_rotvec([0.0, np.radians(yaw_deg_per_m * step), 0.0]).as_matrix()
        noise = Rotation.from_rotvec(rng.normal(0.0, np.radians(step_rot_deg), 3)).as_matrix()
        rel_d = _pose(bias @ noise @ rel[:3, :3], scale * rel[:3, 3] + rng.normal(0.0, step_trans_m, 3))
        out.append(out[-1] @ rel_d)
    return np.stack(out)


def make_side(seed: int = 0, n_kf: int = 60, n_points: int = 900, keep_prob: float = 0.45,
              outlier_frac: float = 0.0, yaw_deg_per_m: float = 0.05) -> Side:
    rng = np.random.default_rng(seed)
    # Truth: sideways along x at 10 cm per keyframe, small wobble in height, depth and heading.
    x = 0.1 * np.arange(n_kf)
    wob = Rotation.from_rotvec(rng.normal(0.0, np.radians(0.5), (n_kf, 3))).as_matrix()  # (K, 3, 3)
    wob[0] = np.eye(3)
    t = np.stack([x, 0.02 * np.sin(x), 0.03 * np.sin(0.7 * x)], axis=1)
    t[0] = 0.0
    truth = np.stack([_pose(wob[k], t[k]) for k in range(n_kf)])
    drifted = _drift(truth, rng, yaw_deg_per_m=yaw_deg_per_m)

    # Landmarks: 60 % on the row (1.25 m +- 0.25), 30 % over 0.2-5 m, 10 % background at 6-10 m.
    kind = rng.choice(3, n_points, p=[0.6, 0.3, 0.1])
    z = np.where(kind == 0, np.clip(rng.normal(1.25, 0.25, n_points), 0.3, 5.0),
                 np.where(kind == 1, rng.uniform(0.2, 5.0, n_points), rng.uniform(6.0, 10.0, n_points)))
    px = rng.uniform(-0.5 * z, x[-1] + 0.5 * z)
    py = rng.uniform(-0.38, 0.38, n_points) * z
    points = np.stack([px, py, z], axis=1)  # (L, 3)

    # Project into every keyframe: visibility, detection dropout, noise.
    T_cam_odom = np.linalg.inv(truth)  # (K, 4, 4)
    pc = np.einsum("kij,lj->kli", T_cam_odom[:, :3, :3], points) + T_cam_odom[:, None, :3, 3]  # (K, L, 3)
    zc = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = INTR.fx * pc[..., 0] / zc + INTR.cx
        v = INTR.fy * pc[..., 1] / zc + INTR.cy
    vis = (zc > 0.1) & (u >= 0) & (u < INTR.width) & (v >= 0) & (v < INTR.height)
    vis &= rng.random(vis.shape) < keep_prob
    kf, lm = np.nonzero(vis)  # keyframe-major: the first observation of a landmark is its earliest
    m = kf.size
    uv = np.stack([u[kf, lm], v[kf, lm]], axis=1) + rng.normal(0.0, 0.5, (m, 2))
    zt = zc[kf, lm]
    depth = zt + rng.normal(0.0, 1.0, m) * 0.004 * zt**2
    depth[(rng.random(m) < 0.1) | (zt > 6.0)] = 0.0
    outlier = rng.random(m) < outlier_frac
    ang = rng.uniform(0.0, 2 * np.pi, m)
    mag = rng.uniform(20.0, 50.0, m)
    uv[outlier] += (mag[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1))[outlier]

    # Initial landmarks: back-project the first observation with depth through the drifted pose.
    init = np.full_like(points, np.nan)
    order = np.flatnonzero(depth > 0)
    _, first = np.unique(lm[order], return_index=True)
    sel = order[first]
    ray = np.stack([(uv[sel, 0] - INTR.cx) / INTR.fx, (uv[sel, 1] - INTR.cy) / INTR.fy, np.ones(sel.size)], axis=1)
    pcam = ray * depth[sel, None]
    Td = drifted[kf[sel]]
    init[lm[sel]] = np.einsum("nij,nj->ni", Td[:, :3, :3], pcam) + Td[:, :3, 3]

    obs = Observations(keyframe=kf.astype(np.int64), landmark=lm.astype(np.int64), uv=uv, depth=depth)
    return Side(truth, drifted, points, init, obs, outlier)


def ate(est: np.ndarray, truth: np.ndarray, with_scale: bool = False) -> float:
    """RMSE (m) of positions after rigid (or similarity) alignment onto the truth."""
    sim = umeyama(est[:, :3, 3], truth[:, :3, 3], with_scale=with_scale)
    aligned = sim.s * est[:, :3, 3] @ sim.R.T + sim.t
    return float(np.sqrt(np.mean(np.sum((aligned - truth[:, :3, 3]) ** 2, axis=1))))


pytestmark = pytest.mark.accuracy


@pytest.fixture(scope="module")
def side(seed_offset) -> Side:
    return make_side(seed=1 + 10 * seed_offset)


@pytest.fixture(scope="module")
def side_outliers(seed_offset) -> Side:
    return make_side(seed=2 + 10 * seed_offset, outlier_frac=0.04)


N_DRAWS = 8  # sides over which a BA variant is compared with the global BA (ATE ratios of ~1 mm ATEs are noisy)


@pytest.fixture(scope="module")
def draws(seed_offset) -> list[tuple[Side, BAResult]]:
    """N_DRAWS synthetic sides with their global RGB-D BA. One draw's ATE ratio of a variant to the global BA
    spreads widely (a cap of 6 observations a track: median 1.19, max 1.69 over 80 draws; windowed: median
    1.06, max 1.31 over 40); means over eight draws spread far less."""
    out = []
    for j in range(N_DRAWS):
        sd = make_side(seed=1 + 10 * seed_offset + 100 * j)
        out.append((sd, bundle_adjust(sd.drifted, sd.init_points, sd.obs, INTR, mode="rgbd", pixel_sigma=0.5)))
    return out


@pytest.fixture(scope="module")
def rgbd_result(side) -> tuple[BAResult, float]:
    t0 = time.perf_counter()
    res = bundle_adjust(side.drifted, side.init_points, side.obs, INTR, mode="rgbd", pixel_sigma=0.5)
    return res, time.perf_counter() - t0


# ------------------------------------------------------------------- RGB-D BA


def test_synthetic_side_is_orchard_like(side):
    assert len(side.truth) == 60
    assert 4000 <= len(side.obs) <= 7000
    assert np.isclose(path_length(side.truth[:, :3, 3]), 5.9, atol=0.1)
    assert 0.05 < np.mean(side.obs.depth == 0) < 0.35
    # the planted drift is about 1 % of the path at the end
    end_err = np.linalg.norm(side.drifted[-1, :3, 3] - side.truth[-1, :3, 3])
    assert 0.03 < end_err < 0.12


def test_rgbd_ba_removes_drift(side, rgbd_result, accuracy):
    res, seconds = rgbd_result
    path = path_length(side.truth[:, :3, 3])
    ate0, ate1 = ate(side.drifted, side.truth), ate(res.poses, side.truth)
    print(f"\nRGB-D BA: {len(side.truth)} keyframes, {len(side.obs)} observations, "
          f"{res.n_landmarks_used} landmarks, {res.n_factors} factors, {res.iterations} iterations, "
          f"{seconds:.2f} s (BAResult.seconds {res.seconds:.2f}); ATE {ate0 * 1e3:.2f} -> {ate1 * 1e3:.2f} mm")
    accuracy.at_least("ATE drifted / after RGB-D BA", ate0 / ate1, 5)
    accuracy.at_most("ATE after RGB-D BA, fraction of path", ate1 / path, 0.001)
    assert res.final_error < res.initial_error
    # keyframe 0 is the gauge: it stays put
    np.testing.assert_allclose(res.poses[0], side.drifted[0], atol=1e-6)
    # landmarks come back near the truth (median error well under a centimetre)
    ok = np.all(np.isfinite(res.landmarks), axis=1)
    assert ok.sum() == res.n_landmarks_used
    near = ok & (side.points[:, 2] < 5.0)
    accuracy.at_most("landmark median error after RGB-D BA, m",
                     np.median(np.linalg.norm(res.landmarks[near] - side.points[near], axis=1)), 0.01)


def test_rgbd_ba_result_shapes(side, rgbd_result):
    res, _ = rgbd_result
    assert res.poses.shape == side.truth.shape
    assert res.landmarks.shape == side.points.shape
    # landmarks seen once or without any depth (no initial position) are not optimised
    counts = np.bincount(side.obs.landmark, minlength=len(side.points))
    skipped = (counts < 2) | ~np.all(np.isfinite(side.init_points), axis=1)
    assert np.all(np.isnan(res.landmarks[skipped]))
    assert res.n_landmarks_used == int((~skipped).sum())
    assert res.n_factors == int(np.sum(~skipped[side.obs.landmark])) + 1  # + gauge prior


def test_windowed_ba_is_as_accurate_as_global_ba(draws, accuracy):
    """Three windows of 30 keyframes (10 left to the next, 5 held) over each 60-keyframe side: memory of a
    window, accuracy of the global BA (each landmark here is seen over up to 5 m: a long track)."""
    ratios = []
    for sd, glob in draws:
        win = bundle_adjust_windowed(sd.drifted, sd.init_points, sd.obs, INTR, window=30, window_tail=10,
                                     window_hold=5, pixel_sigma=0.5)
        ate_g, ate_w = ate(glob.poses, sd.truth), ate(win.poses, sd.truth)
        print(f"\nATE global {ate_g * 1e3:.2f} mm, windowed {ate_w * 1e3:.2f} mm")
        ratios.append(ate_w / ate_g)
        accuracy.at_most("ATE after windowed BA, fraction of path", ate_w / path_length(sd.truth[:, :3, 3]), 0.001)
        np.testing.assert_allclose(win.poses[0], sd.drifted[0], atol=1e-6)  # the gauge stays put
        assert win.n_landmarks_used >= 0.95 * glob.n_landmarks_used
    accuracy.at_most(f"ATE windowed / global BA, mean over {N_DRAWS} sides", np.mean(ratios), 1.5)
    sd = draws[0][0]
    with pytest.raises(ReconstructionError, match="window_hold"):
        bundle_adjust_windowed(sd.drifted, sd.init_points, sd.obs, INTR, window=10, window_tail=8, window_hold=5)


def test_track_cap_keeps_ba_accurate(draws, accuracy):
    """At most 8 observations per landmark, spread over its track (here 5 in the median, up to 33): 15 % of
    the factors go, the accuracy stays (mean ATE ratio over 8 sides 1.09-1.21 at seed offsets 0-3; with
    6 observations a quarter of the factors go and it was 1.15-1.43, one side 2.3)."""
    ratios = []
    for sd, glob in draws:
        capped = bundle_adjust(sd.drifted, sd.init_points, sd.obs, INTR, pixel_sigma=0.5, max_track=8)
        assert capped.n_factors < 0.9 * glob.n_factors
        ate_c = ate(capped.poses, sd.truth)
        ratios.append(ate_c / ate(glob.poses, sd.truth))
        accuracy.at_most("ATE with 8 observations per landmark, fraction of path",
                         ate_c / path_length(sd.truth[:, :3, 3]), 0.001)
    accuracy.at_most(f"ATE with 8 observations per landmark / all, mean over {N_DRAWS} sides", np.mean(ratios), 1.6)


def test_huber_keeps_ba_accurate_with_outliers(side_outliers, accuracy):
    s = side_outliers
    assert 0.02 < s.outlier.mean() < 0.06
    path = path_length(s.truth[:, :3, 3])
    robust = bundle_adjust(s.drifted, s.init_points, s.obs, INTR, pixel_sigma=0.5)
    plain = bundle_adjust(s.drifted, s.init_points, s.obs, INTR, pixel_sigma=0.5, huber_k=None)
    ate0, ate_r, ate_p = ate(s.drifted, s.truth), ate(robust.poses, s.truth), ate(plain.poses, s.truth)
    print(f"\noutliers {s.outlier.mean():.1%}: ATE drifted {ate0 * 1e3:.2f} mm, Huber {ate_r * 1e3:.2f} mm, "
          f"least squares {ate_p * 1e3:.2f} mm")
    accuracy.at_least("ATE drifted / after robust BA with outliers", ate0 / ate_r, 5)
    accuracy.at_most("ATE after robust BA with outliers, fraction of path", ate_r / path, 0.001)
    assert ate_r < ate_p


def test_the_depth_residuals_say_how_noisy_the_depth_was(side, rgbd_result):
    """disparity_residual_sd: at the true poses and landmarks the planted depth noise (0.004 z^2, i.e.
    0.004 fx b = 0.123 px of disparity) comes back, twice the noise gives twice the sd, and the BA's own
    residuals are somewhat smaller (each landmark's depth is fitted to its observations)."""
    o = side.obs
    pure = default_disparity_sigma(INTR.fx, 0.05)  # px
    sd = disparity_residual_sd(side.truth, side.points, o.keyframe, o.landmark, o.depth, INTR.fx, 0.05)
    assert sd == pytest.approx(pure, rel=0.1)
    T_cam_odom = np.linalg.inv(side.truth[o.keyframe])  # (M, 4, 4)
    z = np.einsum("mj,mj->m", T_cam_odom[:, 2, :3], side.points[o.landmark]) + T_cam_odom[:, 2, 3]  # (M,)
    doubled = np.where(o.depth > 0, z + 2.0 * (o.depth - z), 0.0)
    sd2 = disparity_residual_sd(side.truth, side.points, o.keyframe, o.landmark, doubled, INTR.fx, 0.05)
    assert sd2 == pytest.approx(2 * pure, rel=0.1)
    res, _ = rgbd_result
    assert 0.5 * pure < res.disparity_residual_sd < 1.05 * pure


def test_default_disparity_sigma_matches_realsense_depth_noise():
    # depth sd = z^2 sd_d / (fx b) = 0.004 z^2
    sd_d = default_disparity_sigma(615.0, 0.05)
    assert sd_d == pytest.approx(0.123)
    for z in (0.5, 1.25, 4.0):
        assert z**2 * sd_d / (615.0 * 0.05) == pytest.approx(0.004 * z**2)


def test_keyframe_without_observations_is_bridged(caplog):
    s = make_side(seed=5, n_kf=20, n_points=300)
    keep = s.obs.keyframe != 10
    obs = Observations(s.obs.keyframe[keep], s.obs.landmark[keep], s.obs.uv[keep], s.obs.depth[keep])
    with caplog.at_level("WARNING", logger="orchard_mapping.core.bundle_adjustment"):
        res = bundle_adjust(s.drifted, s.init_points, obs, INTR, pixel_sigma=0.5)
    assert "keyframes [10]" in caplog.text
    assert np.all(np.isfinite(res.poses))
    assert ate(res.poses, s.truth) < ate(s.drifted, s.truth)


# --------------------------------------------------------------------- RGB BA


@pytest.fixture(scope="module")
def side_yaw_drift(seed_offset) -> Side:
    """The planted drift of `side` (1 % scale, 0.05 deg/m yaw) is nearly all scale, which the sim(3) alignment
    of a colour-only map removes: what is left sits near the noise floor (measured: BA improved on it only
    2.3-3.8x over four seeds, a ratio of floors). A colour-only front end drifts in yaw too: 0.3 deg/m."""
    return make_side(seed=3 + 10 * seed_offset, yaw_deg_per_m=0.3)


def test_rgb_only_ba_reduces_sim3_ate(side_yaw_drift, accuracy):
    side = side_yaw_drift
    rgb_obs = replace(side.obs, depth=np.zeros_like(side.obs.depth))
    res = bundle_adjust(side.drifted, side.init_points, rgb_obs, INTR, mode="rgb", pixel_sigma=0.5)
    ate0 = ate(side.drifted, side.truth, with_scale=True)
    ate1 = ate(res.poses, side.truth, with_scale=True)
    print(f"\nRGB-only BA: sim(3) ATE {ate0 * 1e3:.2f} -> {ate1 * 1e3:.2f} mm in {res.iterations} iterations")
    accuracy.at_least("sim(3) ATE drifted / after RGB-only BA", ate0 / ate1, 2)
    accuracy.at_most("sim(3) ATE after RGB-only BA, fraction of path", ate1 / path_length(side.truth[:, :3, 3]), 0.001)
    assert res.final_error < res.initial_error
    # the scale gauge: the distance keyframe 0 -> farthest keyframe is held
    d0 = np.linalg.norm(side.drifted[-1, :3, 3] - side.drifted[0, :3, 3])
    d1 = np.linalg.norm(res.poses[-1, :3, 3] - res.poses[0, :3, 3])
    assert d1 == pytest.approx(d0, rel=1e-4)
    # depth is ignored in RGB mode: the same call with depth gives the same answer
    res_d = bundle_adjust(side.drifted, side.init_points, side.obs, INTR, mode="rgb", pixel_sigma=0.5)
    np.testing.assert_allclose(res_d.poses, res.poses, atol=1e-9)


def test_rgb_only_ba_holds_the_distance_to_the_chosen_scale_anchor(side):
    """scale_anchor: the keyframe whose distance to keyframe 0 is the scale gauge (the colour-only front end's
    re-entry BA holds the keyframes before a gap this way); other distances are free."""
    rgb_obs = replace(side.obs, depth=np.zeros_like(side.obs.depth))
    res = bundle_adjust(side.drifted, side.init_points, rgb_obs, INTR, mode="rgb", pixel_sigma=0.5, scale_anchor=20)
    d0 = np.linalg.norm(side.drifted[20, :3, 3] - side.drifted[0, :3, 3])
    assert np.linalg.norm(res.poses[20, :3, 3] - res.poses[0, :3, 3]) == pytest.approx(d0, rel=1e-4)
    with pytest.raises(ReconstructionError, match="scale_anchor"):
        bundle_adjust(side.drifted, side.init_points, rgb_obs, INTR, mode="rgb", scale_anchor=0)


# ----------------------------------------------------------------- pose graph


def _square_path(side_m: float = 2.0, step: float = 0.1) -> np.ndarray:
    """Closed square walk, turning 90 deg about the camera's vertical (y) at each corner."""
    poses, T = [np.eye(4)], np.eye(4)
    n_side = int(round(side_m / step))
    for _ in range(4):
        for i in range(n_side):
            rel = _pose(np.eye(3), [0.0, 0.0, step])
            if i == n_side - 1:
                rel[:3, :3] = Rotation.from_rotvec([0.0, np.pi / 2, 0.0]).as_matrix()
            T = T @ rel
            poses.append(T.copy())
    return np.stack(poses)


def test_pose_graph_loop_closure_pulls_last_pose_back():
    truth = _square_path()
    rng = np.random.default_rng(3)
    # a closed walk hides a scale error from a loop closure (a pure scale keeps it closed),
    # so the planted drift here is a yaw bias plus random steps
    drifted = _drift(truth, rng, scale=1.0, yaw_deg_per_m=0.3, step_rot_deg=0.01, step_trans_m=0.001)
    last = len(truth) - 1
    assert np.linalg.norm(drifted[last, :3, 3] - truth[last, :3, 3]) > 0.05
    loop = LoopClosure(kf_a=0, kf_b=last, T_a_b=np.linalg.inv(truth[0]) @ truth[last], inliers=200, score=0.9)
    out = optimise_pose_graph(drifted, [loop], sigma_rot_deg=0.1, sigma_trans_m=0.005,
                              loop_sigma_rot_deg=0.05, loop_sigma_trans_m=0.001)
    err_last = np.linalg.norm(out[last, :3, 3] - truth[last, :3, 3])
    print(f"\npose graph: last pose error {np.linalg.norm(drifted[last, :3, 3] - truth[last, :3, 3]) * 1e3:.1f}"
          f" -> {err_last * 1e3:.2f} mm; ATE {ate(drifted, truth) * 1e3:.1f} -> {ate(out, truth) * 1e3:.1f} mm")
    assert err_last < 0.005
    assert ate(out, truth) < 0.35 * ate(drifted, truth)
    np.testing.assert_allclose(out[0], drifted[0], atol=1e-6)  # gauge


def test_pose_graph_without_loops_keeps_the_odometry():
    truth = _square_path(side_m=1.0)
    drifted = _drift(truth, np.random.default_rng(4))
    out = optimise_pose_graph(drifted, [])
    np.testing.assert_allclose(out, drifted, atol=1e-6)


def test_ba_with_loop_closure_factor(side):
    # a true loop between the first and last keyframe is consistent with the data
    loop = LoopClosure(0, len(side.truth) - 1, np.linalg.inv(side.truth[0]) @ side.truth[-1], 100, 1.0)
    res = bundle_adjust(side.drifted, side.init_points, side.obs, INTR, loops=[loop], pixel_sigma=0.5,
                        loop_sigma_trans_m=0.002, loop_sigma_rot_deg=0.05)
    assert ate(res.poses, side.truth) < 0.001 * path_length(side.truth[:, :3, 3])


# --------------------------------------------------------------------- errors


def test_bad_landmark_id_raises_typed_error(side):
    bad = replace(side.obs, landmark=side.obs.landmark.copy())
    bad.landmark[5] = len(side.points) + 7
    with pytest.raises(ReconstructionError, match=r"observation 5 names landmark"):
        bundle_adjust(side.drifted, side.init_points, bad, INTR)
    assert issubclass(ReconstructionError, OrchardMappingError)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda s: dict(obs=replace(s.obs, keyframe=s.obs.keyframe + 100)), "names keyframe"),
        (lambda s: dict(obs=replace(s.obs, uv=s.obs.uv[:, :1])), "uv"),
        (lambda s: dict(poses=s.drifted[:, :3]), "poses must be"),
        (lambda s: dict(landmarks=s.init_points[:, :2]), "landmarks must be"),
        (lambda s: dict(mode="mono"), "mode"),
        (lambda s: dict(loops=[LoopClosure(0, 999, np.eye(4), 10, 1.0)]), "loop closure 0"),
        (lambda s: dict(obs=replace(s.obs, depth=-s.obs.depth - 1.0)), "negative"),
    ],
)
def test_inconsistent_inputs_raise_typed_errors(side, mutate, match):
    kw = dict(poses=side.drifted, landmarks=side.init_points, obs=side.obs, intr=INTR)
    kw.update(mutate(side))
    with pytest.raises(ReconstructionError, match=match):
        bundle_adjust(**kw)


def test_pose_graph_rejects_bad_loop():
    with pytest.raises(ReconstructionError, match="keyframe"):
        optimise_pose_graph(np.tile(np.eye(4), (3, 1, 1)), [LoopClosure(0, 3, np.eye(4), 10, 1.0)])


def _noisy_pose_graph(n: int, seed: int):
    """A chain of n poses with skip links, robust noise, started far from the solution."""
    import gtsam

    rng = np.random.default_rng(seed)
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                                           gtsam.noiseModel.Isotropic.Sigma(6, 0.05))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    for i in range(n):
        values.insert(i, gtsam.Pose3(gtsam.Rot3.Rodrigues(*rng.normal(0, 0.2, 3)), rng.normal(0, 0.5, 3)))
        for k in (1, 4):
            if i >= k:
                step = gtsam.Pose3(gtsam.Rot3.Rodrigues(0.0, 0.01 * k, 0.0), np.array([0.1 * k, 0.0, 0.0]))
                graph.add(gtsam.BetweenFactorPose3(i - k, i, step, noise))
    return graph, values


def test_optimising_in_steps_is_optimize_and_lets_other_threads_run():
    """optimise_in_steps gives GTSAM's optimize() result to the bit, and another thread of the process
    runs between its iterations (optimize() holds the GIL throughout: the live odometry node lost frames)."""
    import threading

    import gtsam

    from orchard_mapping.core.bundle_adjustment import optimise_in_steps

    graph, values = _noisy_pose_graph(300, 0)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(30)
    params.setRelativeErrorTol(1e-5)
    whole = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    want = whole.optimize()
    stepped = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
    ticks, stop = [], threading.Event()

    def tick() -> None:
        while not stop.is_set():
            ticks.append(stepped.iterations())

    t = threading.Thread(target=tick)
    t.start()
    try:
        got = optimise_in_steps(stepped, params)
    finally:
        stop.set()
        t.join()
    assert stepped.iterations() == whole.iterations() >= 3
    for i in range(300):
        assert np.array_equal(got.atPose3(i).matrix(), want.atPose3(i).matrix()), i
    # the other thread ran while the optimisation was between its first and its last iteration
    assert len({k for k in ticks if 0 < k < stepped.iterations()}) >= 1, sorted(set(ticks))
