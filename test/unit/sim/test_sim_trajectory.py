"""Camera paths: truth trajectories against the bags, and the shape of each path mode.

Hand-held jitter (path.jitter_m = 12 mm, path.jitter_deg = 0.8 deg, both RMS of a sum of sinusoids, so
peaks reach ~3x) sets the tolerances on heights and angles below.
"""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.config import TopicsConfig
from orchard_mapping.io.bags import describe_bag, read_rgbd

TOPICS = TopicsConfig()


def _pitch_and_height(run, side: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per truth frame: pitch of the optical axis (deg, + up), camera height above the terrain (m), world poses."""
    _, poses = run.world_poses(side)
    fwd = poses[:, :3, 2]  # optical z in world
    pitch = np.degrees(np.arcsin(np.clip(fwd[:, 2], -1, 1)))
    p = poses[:, :3, 3]
    height = p[:, 2] - run.scene.terrain.height(p[:, 0], p[:, 1])
    return pitch, height, poses


@pytest.fixture(scope="module")
def loop_sim(make_sim, tiny_row):
    return make_sim("standard", {**tiny_row, "path.mode": "loop"}, 5)


def test_truth_stamps_are_bag_colour_stamps(standard_sim):
    for side in ("front", "back"):
        stamps, _ = standard_sim.world_poses(side)
        seq = read_rgbd(standard_sim.result.bags[side])
        assert len(seq) == len(stamps) == standard_sim.result.frames[side]
        np.testing.assert_allclose(seq.stamps, stamps, rtol=0, atol=1e-6)  # TUM rows round stamps to 1 us
        assert np.all(np.diff(stamps) > 0)
        topics = {name: count for name, _, count in describe_bag(standard_sim.result.bags[side]).topics}
        assert topics == {TOPICS.color: len(stamps), TOPICS.depth: len(stamps), TOPICS.camera_info: len(stamps)}
        # Frame spacing is the camera rate.
        np.testing.assert_allclose(np.diff(stamps), 1 / standard_sim.scenario.camera.rate_hz, atol=2e-6)
    front, _ = standard_sim.world_poses("front")
    back, _ = standard_sim.world_poses("back")
    assert back[0] > front[-1]  # the back side is recorded after the front side


def test_two_sweep_level_then_raised(standard_sim):
    """Each side: a level sweep at low_height_m, then back along the row raised to high_height_m, tilted down."""
    p = standard_sim.scenario.path
    for side in ("front", "back"):
        pitch, height, poses = _pitch_and_height(standard_sim, side)
        level = (np.abs(pitch) < 4.0) & (np.abs(height - p.low_height_m) < 0.08)
        raised = (np.abs(pitch + p.high_tilt_deg) < 4.0) & (np.abs(height - p.high_height_m) < 0.08)
        n = len(pitch)
        assert level.sum() >= 0.3 * n and raised.sum() >= 0.3 * n, (level.sum(), raised.sum(), n)
        # Level sweep first, raised sweep last (the turn at the row end lies between).
        assert np.flatnonzero(level).max() < np.flatnonzero(raised).min()
        assert level[0] and raised[-1]
        assert np.median(height[raised]) - np.median(height[level]) == pytest.approx(p.high_height_m - p.low_height_m, abs=0.05)
        assert np.median(pitch[raised]) == pytest.approx(-p.high_tilt_deg, abs=1.0)
        assert np.median(pitch[level]) == pytest.approx(0.0, abs=1.0)
        # The camera stands on its side of the row, looking across it, and returns a little further out.
        sgn = -1.0 if side == "front" else 1.0
        np.testing.assert_allclose(poses[level, 1, 3], sgn * p.distance_m, atol=0.06)
        np.testing.assert_allclose(poses[raised, 1, 3], sgn * p.high_distance_m, atol=0.06)
        look = poses[:, :3, 2][:, :2]
        assert np.all(look[:, 1] * -sgn > 0.85 * np.linalg.norm(look, axis=1))
        x = poses[:, 0, 3]
        walk = np.sign(x[np.flatnonzero(level)[-1]] - x[0])
        assert walk == (1.0 if side == "front" else -1.0)  # front walked towards +x, back towards -x
        assert abs(x[-1] - x[0]) < 0.1  # the raised sweep ends where the level sweep began


def test_single_pass_has_no_raised_part(tiny_single_pass):
    p = tiny_single_pass.scenario.path
    for side in ("front", "back"):
        pitch, height, _ = _pitch_and_height(tiny_single_pass, side)
        assert np.all(np.abs(pitch) < 4.0)
        assert np.all(np.abs(height - p.low_height_m) < 0.08)


def test_loop_mode_one_bag_with_side_topic(loop_sim):
    run = loop_sim
    assert set(run.result.bags) == {"loop"}
    assert sorted(q.name for q in run.out.iterdir() if q.is_dir()) == ["loop", "masks"]
    topics = {name: (t, c) for name, t, c in describe_bag(run.result.bags["loop"]).topics}
    assert topics[TOPICS.side] == ("std_msgs/msg/String", 2)  # written on each change: front, then back
    seq = read_rgbd(run.result.bags["loop"])
    sides = list(seq.sides)
    k = sides.index("back")
    assert k > 0 and sides[:k] == ["front"] * k and sides[k:] == ["back"] * (len(sides) - k)
    # Both sides' truth is there and together they are the bag's frames, in order.
    truth = run.truth
    assert truth["sides"]["front"]["bag"] == truth["sides"]["back"]["bag"] == "loop"
    sf, _ = run.world_poses("front")
    sb, _ = run.world_poses("back")
    assert len(sf) == k and len(sb) == len(sides) - k
    np.testing.assert_allclose(np.concatenate([sf, sb]), seq.stamps, atol=1e-6)
    # One continuous drive: both sides share the odometry frame of the first frame.
    np.testing.assert_allclose(truth["T_front_back"], np.eye(4), atol=1e-9)
    # The drive goes round the row end: the front part at y < 0, the back part at y > 0.
    _, pf = run.world_poses("front")
    _, pb = run.world_poses("back")
    assert pf[0, 1, 3] < -1.0 and pb[-1, 1, 3] > 1.0
    assert np.all(pf[:, 1, 3] < 0.2) and np.all(pb[:, 1, 3] > -0.2)
