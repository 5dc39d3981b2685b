"""core.geometry: rotations, similarity alignment, path length."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orchard_mapping.core.geometry import (
    decompose_similarity,
    make_transform,
    matrix_to_quat,
    path_length,
    pose_matrices,
    quat_to_matrix,
    rotation_angle_deg,
    transform_points,
    umeyama,
)
from orchard_mapping.errors import AlignmentError


def test_quaternion_round_trip_and_scalar_last() -> None:
    rng = np.random.default_rng(0)
    R = Rotation.random(20, random_state=1).as_matrix()
    q = matrix_to_quat(R)
    assert q.shape == (20, 4) and np.all(q[:, 3] >= 0)
    np.testing.assert_allclose(quat_to_matrix(q), R, atol=1e-12)
    # scalar last: 90 deg about z
    np.testing.assert_allclose(
        quat_to_matrix([0, 0, np.sqrt(0.5), np.sqrt(0.5)]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12
    )
    # unnormalised input is normalised
    np.testing.assert_allclose(quat_to_matrix(3.0 * q[0]), R[0], atol=1e-12)
    T = pose_matrices(rng.normal(size=(20, 3)), q)
    assert T.shape == (20, 4, 4)
    np.testing.assert_allclose(T[:, :3, :3], R, atol=1e-12)


@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_known_transform(with_scale: bool) -> None:
    rng = np.random.default_rng(2)
    src = rng.normal(size=(50, 3))
    R = Rotation.from_euler("xyz", [10, -25, 70], degrees=True).as_matrix()
    s = 1.7 if with_scale else 1.0
    dst = transform_points(make_transform(R, [0.3, -2.0, 5.0], s), src)
    sim = umeyama(src, dst, with_scale=with_scale)
    np.testing.assert_allclose(sim.R, R, atol=1e-10)
    np.testing.assert_allclose(sim.t, [0.3, -2.0, 5.0], atol=1e-10)
    assert sim.s == pytest.approx(s, abs=1e-10)
    back = decompose_similarity(sim.matrix())
    assert back.s == pytest.approx(s) and np.allclose(back.R, R)


def test_umeyama_rejects_degenerate_input() -> None:
    with pytest.raises(AlignmentError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(AlignmentError, match="coincide"):
        umeyama(np.ones((5, 3)), np.zeros((5, 3)))


def test_rotation_angle_and_path_length() -> None:
    for deg in (0.0, 1e-4, 2.0, 90.0, 179.0):
        R = Rotation.from_rotvec(np.radians(deg) * np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5]))
        assert rotation_angle_deg(R.as_matrix()) == pytest.approx(deg, abs=1e-9)
    assert path_length(np.array([[0, 0, 0], [3, 4, 0], [3, 4, 1]])) == pytest.approx(6.0)
    assert path_length(np.zeros((1, 3))) == 0.0
    with pytest.raises(ValueError):
        decompose_similarity(np.diag([1.0, 1.0, -1.0, 1.0]))


def test_points_move_with_their_nearest_keyframe():
    """A side bent by the merge: each point follows the keyframe whose camera is nearest (the cloud of
    merged.ply and the evaluator's trunk axes), and an unmoved side stays where it was."""
    from orchard_mapping.core.geometry import make_transform, move_with_keyframes

    rng = np.random.default_rng(0)
    before = np.stack([make_transform(np.eye(3), np.array([x, 0.0, 0.0])) for x in (0.0, 5.0, 10.0)])
    pts = np.concatenate([c + rng.normal(0, 0.5, (50, 3)) for c in before[:, :3, 3]])  # (150, 3) near each camera
    assert np.allclose(move_with_keyframes(pts, before, before), pts)
    lift = np.array([0.0, 0.0, 0.01])  # the last keyframe 1 cm up, the middle one turned 90 deg about z
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    after = before.copy()
    after[2, :3, 3] += lift
    after[1, :3, :3] = Rz
    moved = move_with_keyframes(pts, before, after)
    assert np.allclose(moved[:50], pts[:50])
    assert np.allclose(moved[100:], pts[100:] + lift)
    c = before[1, :3, 3]
    assert np.allclose(moved[50:100], (pts[50:100] - c) @ Rz.T + c)  # turned about its own camera
    assert move_with_keyframes(np.zeros((0, 3)), before, after).shape == (0, 3)
