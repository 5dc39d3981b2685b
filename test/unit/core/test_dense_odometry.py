"""Dense RGB-D odometry baseline (orchard_mapping/core/dense_odometry.py) on simulated frames.

The recording: 6 consecutive frames of the front side's level sweep of a 2-tree row, 640x480 at
15 Hz (the benchmark's camera, ~4 cm between frames), with the simulator's noise (depth sd
0.004 z^2, dropouts, flying pixels, exposure jitter). Truth: the camera path's poses.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from orchard_mapping.core.dense_odometry import DenseOdometryError, dense_rgbd_odometry, dense_rgbd_odometry_result
from orchard_mapping.core.geometry import rotation_angle_deg
from orchard_mapping.core.types import RGBDFrame
from orchard_mapping.errors import OrchardMappingError
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import Rig

SEED = 11
N_FRAMES = 6


pytestmark = pytest.mark.accuracy


@pytest.fixture(scope="module")
def recording(seed_offset) -> tuple[list[RGBDFrame], np.ndarray]:
    """(frames, true T_world_cam (N, 4, 4)) from the middle of the level sweep, where trees fill the view."""
    seed = SEED + seed_offset
    sc = load_scenario("standard", {"row.n_trees": 2, "camera.rate_hz": 15})
    rig = Rig.build(sc, seed)
    intr = rig.intrinsics
    path = rig.path("front", np.random.default_rng(seed))
    rng = np.random.default_rng([seed, 2])
    start = len(path.stamps) // 3
    frames = []
    for k in range(start, start + N_FRAMES):
        t = float(path.stamps[k])
        color, depth, _ = rig.shoot(path.poses[k], rng, t)
        frames.append(RGBDFrame(t, color, depth, intr, "front", k))
    return frames, path.poses[start:start + N_FRAMES]


def _relative_errors(est: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per consecutive pair: translation error (mm), rotation error (deg), true step (mm)."""
    dt, dr, step = [], [], []
    for k in range(1, len(est)):
        rel_est = np.linalg.inv(est[k - 1]) @ est[k]
        rel_true = np.linalg.inv(true[k - 1]) @ true[k]
        d = np.linalg.inv(rel_true) @ rel_est
        dt.append(1000 * np.linalg.norm(d[:3, 3]))
        dr.append(rotation_angle_deg(d[:3, :3]))
        step.append(1000 * np.linalg.norm(rel_true[:3, 3]))
    return np.array(dt), np.array(dr), np.array(step)


# Per-pair tolerances (translation mm median / max, rotation deg median / max), with each method's
# default settings. Measured: point-to-plane 1.2 (1.7) mm, 0.06 (0.12) deg on ~22 mm steps (it slides
# along the row); hybrid (point-to-plane, then the photometric term) 0.4 (1.2) mm, 0.01 (0.02) deg.
TOLERANCES = {
    "point_to_plane": (3.0, 5.0, 0.15, 0.3),
    "hybrid": (1.0, 2.5, 0.03, 0.1),
}


@pytest.mark.parametrize("method", sorted(TOLERANCES))
def test_relative_motion_matches_truth(recording, method, accuracy):
    frames, true = recording
    stamps, poses = dense_rgbd_odometry(frames, method=method)
    assert stamps.shape == (N_FRAMES,) and poses.shape == (N_FRAMES, 4, 4)
    np.testing.assert_allclose(stamps, [f.stamp for f in frames])
    np.testing.assert_allclose(poses[0], np.eye(4))  # odom = first camera
    np.testing.assert_allclose(poses[:, :3, :3] @ poses[:, :3, :3].transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), (N_FRAMES, 3, 3)), atol=1e-9)
    dt, dr, step = _relative_errors(poses, true)
    print(f"\ndense {method}: steps {np.median(step):.0f} mm, error per pair median {np.median(dt):.2f} "
          f"(max {dt.max():.2f}) mm, {np.median(dr):.3f} (max {dr.max():.3f}) deg")
    assert np.median(step) > 15  # the camera does move: the errors below are not trivially small
    t_med, t_max, r_med, r_max = TOLERANCES[method]
    accuracy.at_most(f"{method}: median translation error per pair, mm", np.median(dt), t_med)
    accuracy.at_most(f"{method}: largest translation error per pair, mm", dt.max(), t_max)
    accuracy.at_most(f"{method}: median rotation error per pair, deg", np.median(dr), r_med)
    accuracy.at_most(f"{method}: largest rotation error per pair, deg", dr.max(), r_max)


def test_result_reports_timings_and_fitness(recording):
    frames, _ = recording
    r = dense_rgbd_odometry_result(frames[:3], method="intensity")
    assert r.pair_seconds.shape == (2,) and (r.pair_seconds > 0).all()
    assert r.fitness.shape == (2,) and (r.fitness > 0).all()
    assert r.failed_pairs == []
    assert np.isfinite(r.poses).all()


def test_identical_frames_give_identity(recording):
    frames, _ = recording
    same = [frames[0], replace(frames[0], stamp=frames[0].stamp + 0.1)]
    _, poses = dense_rgbd_odometry(same)
    assert np.linalg.norm(poses[1][:3, 3]) < 1e-4
    assert rotation_angle_deg(poses[1][:3, :3]) < 0.01


def test_bad_input_raises_typed_errors(recording):
    frames, _ = recording
    f = frames[0]
    cases = {
        "no depth": [replace(f, depth=None)],
        "uint16 depth": [replace(f, depth=(f.depth * 1000).astype(np.uint16))],
        "size mismatch": [replace(f, depth=f.depth[:-2])],
        "float colour": [replace(f, color=f.color.astype(np.float32))],
        "intrinsics change": [f, replace(frames[1], intrinsics=replace(f.intrinsics, fx=f.intrinsics.fx + 1))],
        "no frames": [],
    }
    assert issubclass(DenseOdometryError, OrchardMappingError)
    for _what, bad in cases.items():  # _what: the case, in a failure's traceback
        with pytest.raises(DenseOdometryError):
            dense_rgbd_odometry(bad)
    with pytest.raises(DenseOdometryError, match="method"):
        dense_rgbd_odometry(frames[:2], method="icp")
    with pytest.raises(DenseOdometryError, match="iterations"):
        dense_rgbd_odometry(frames[:2], iterations=())
    with pytest.raises(DenseOdometryError, match="photometric_init"):
        dense_rgbd_odometry(frames[:2], method="hybrid", photometric_init="zero")


def test_unsolvable_pair_falls_back_to_the_guess(recording):
    frames, _ = recording
    blind = replace(frames[1], depth=np.zeros_like(frames[1].depth))  # no valid depth: nothing to align
    r = dense_rgbd_odometry_result([frames[0], blind, frames[2]])
    assert r.failed_pairs[:1] == [1]
    np.testing.assert_allclose(r.poses[1], np.eye(4))  # the guess: constant velocity from rest
    assert np.isfinite(r.poses).all() and r.pair_seconds.shape == (2,)


def test_implausibly_fast_motion_is_rejected(recording):
    frames, _ = recording
    # Three frames' motion (~6 cm) stamped 1 ms apart: 60 m/s, no hand-held camera moves like that.
    jump = replace(frames[3], stamp=frames[0].stamp + 0.001)
    r = dense_rgbd_odometry_result([frames[0], jump])
    assert r.failed_pairs == [1]
    np.testing.assert_allclose(r.poses[1], np.eye(4))
    assert dense_rgbd_odometry_result([frames[0], frames[3]]).failed_pairs == []
