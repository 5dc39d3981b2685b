"""The merged map's error (eval.metrics.map_merge_error) on a side swept twice along a row, at two heights,
as the simulator's and a hand-held camera's paths are: the fit must weigh each keyframe's position and
orientation as the map does, by what the keyframe sees."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orchard_mapping.core.geometry import matrix_to_quat
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.eval.metrics import fit_map_to_world, map_merge_error, rotation_angle_deg, trajectory_between

# world: x along the row, z up; trunks on y = 0, 10 m of row
BASES = np.c_[np.arange(0.5, 10.0, 1.0), np.zeros(10), np.zeros(10)]  # (10, 3)
SCENE = np.concatenate([BASES, BASES + [0.0, 0.0, 0.7]])  # trunk bases and tops


def _two_sweeps(side_y: float) -> np.ndarray:
    """(K, 4, 4) world: cameras at y = side_y looking across the row at the trunks (optical: z ahead, y
    down), along the row at 0.6 m and back at 3.2 m, tilted down 35 deg there."""
    out = []
    for x, h, tilt in [(x, 0.6, 0.0) for x in np.linspace(0, 10, 60)] + [(x, 3.2, 35.0) for x in np.linspace(10, 0, 60)]:
        ahead = np.array([0.0, -np.sign(side_y), 0.0])
        z = np.cos(np.radians(tilt)) * ahead + np.sin(np.radians(tilt)) * np.array([0.0, 0.0, -1.0])
        y = np.cross(z, np.cross([0.0, 0.0, -1.0], z))
        y /= np.linalg.norm(y)
        T = np.eye(4)
        T[:3, :3] = np.stack([np.cross(y, z), y, z], 1)
        T[:3, 3] = [x, side_y, h]
        out.append(T)
    return np.array(out)


def _traj(T: np.ndarray) -> StampedTrajectory:
    return StampedTrajectory(np.arange(len(T)) * 0.5, T[:, :3, 3], matrix_to_quat(T[:, :3, :3]))


def _seen_misplacement_mm(A: np.ndarray, est: np.ndarray, true: np.ndarray) -> float:
    """RMS (mm) of where A (4, 4) map -> world puts the scene points each keyframe sees, against the truth."""
    errs = []
    for Te, Tt in zip(est, true, strict=True):
        local = (SCENE - Tt[:3, 3]) @ Tt[:3, :3]
        seen = (local[:, 2] > 0.1) & (np.linalg.norm(local, axis=1) < 4.0)
        placed = local[seen] @ Te[:3, :3].T + Te[:3, 3]
        errs.append(placed @ A[:3, :3].T + A[:3, 3] - SCENE[seen])
    return 1000 * float(np.sqrt(np.mean(np.sum(np.concatenate(errs) ** 2, axis=1))))


def test_the_side_is_fitted_on_what_its_keyframes_see() -> None:
    """Every keyframe turned 0.3 deg about the row, about its own centre: the sweep at 3.2 m and the one at
    0.6 m then place the trunks 2 m away differently, and no rigid move undoes both. The fit on the scene
    points leaves the trunks, as the keyframes placed them, closer to the truth than a fit on the keyframes'
    centres and axis points, and the merged map's error differs accordingly; an exact side is fitted exactly."""
    true = _two_sweeps(2.0)
    turned = true.copy()
    turned[:, :3, :3] = Rotation.from_rotvec([np.radians(0.3), 0.0, 0.0]).as_matrix() @ true[:, :3, :3]
    A_scene = fit_map_to_world(_traj(turned), _traj(true), np.eye(4), 0.01, SCENE)
    A_poses = fit_map_to_world(_traj(turned), _traj(true), np.eye(4), 0.01)
    assert _seen_misplacement_mm(A_scene, turned, true) < 0.7 * _seen_misplacement_mm(A_poses, turned, true)
    exact = fit_map_to_world(_traj(true), _traj(true), np.eye(4), 0.01, SCENE)
    np.testing.assert_allclose(exact, np.eye(4), atol=1e-9)

    front = _two_sweeps(-2.0)
    m_scene = map_merge_error(_traj(front), _traj(turned), _traj(front), _traj(true), np.eye(4), np.eye(4), BASES,
                              scene_points=SCENE)
    m_poses = map_merge_error(_traj(front), _traj(turned), _traj(front), _traj(true), np.eye(4), np.eye(4), BASES)
    assert m_scene.rotation_error_deg == pytest.approx(rotation_angle_deg(A_scene[:3, :3]), abs=1e-9)
    assert m_poses.rotation_error_deg == pytest.approx(rotation_angle_deg(A_poses[:3, :3]), abs=1e-9)


def test_a_side_that_sees_no_scene_point_falls_back_to_its_poses() -> None:
    """Keyframes looking away from every trunk: the fit is on their poses, an exact side still exactly."""
    away = _two_sweeps(-2.0)
    away[:, :3, :3] = away[:, :3, :3] @ np.diag([-1.0, 1.0, -1.0])  # turned 180 deg about their y axis
    G = np.eye(4)
    G[:3, 3] = [0.01, 0.0, 0.0]
    np.testing.assert_allclose(fit_map_to_world(_traj(G @ away), _traj(away), np.eye(4), 0.01, SCENE),
                               np.linalg.inv(G), atol=1e-9)


def test_the_trunk_seeing_sweep_leaves_out_the_raised_sweeps_drift() -> None:
    """The back side's raised sweep (its second half, which sees no trunk) turned 0.4 deg about the row: the
    merged map's error with every keyframe shows it; limited to the stamps of the sweep that saw the trunks
    (trajectory_between), the error is that of the merge alone, here none."""
    front, back = _two_sweeps(-2.0), _two_sweeps(2.0)
    drifted = back.copy()
    turn = Rotation.from_rotvec([np.radians(0.4), 0.0, 0.0]).as_matrix()
    drifted[60:, :3, :3] = turn @ back[60:, :3, :3]
    full = map_merge_error(_traj(front), _traj(drifted), _traj(front), _traj(back), np.eye(4), np.eye(4), BASES,
                           scene_points=SCENE)
    assert full.translation_error_mm > 3.0 and full.rotation_error_deg > 0.02
    level = (0.0, 59 * 0.5)  # s: the level sweep's stamps (_traj: 0.5 s apart)
    sweep = map_merge_error(trajectory_between(_traj(front), *level), trajectory_between(_traj(drifted), *level),
                            _traj(front), _traj(back), np.eye(4), np.eye(4), BASES, scene_points=SCENE)
    assert sweep.rotation_error_deg < 1e-6 and sweep.translation_error_mm < 1e-6
    assert len(trajectory_between(_traj(back), *level).stamps) == 60
