"""The side of a continuous drive from the camera's heading (core.sides.UTurnSides)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orchard_mapping.core.sides import UTurnSides


def _drive(turn_sign: float, tilt_deg: float, sway_deg: float, rng: np.random.Generator):
    """World camera poses (optical frame) of a drive along +x looking at +y, a half circle round the row end,
    back along -x looking at -y; and each frame's true side (half of the turn each)."""
    def cam(yaw: float, pos) -> np.ndarray:
        # optical frame: z forward, y down; yaw about world z; a pitch tilt about the camera's x
        look = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        R = np.column_stack([np.cross(look, [0, 0, 1.0]), [0, 0, -1.0], look])
        R = R @ Rotation.from_euler("x", -tilt_deg, degrees=True).as_matrix()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, pos
        return T
    poses, sides = [], []
    base = np.pi / 2
    for x in np.linspace(0, 10, 150):
        poses.append(cam(base + np.radians(rng.normal(0, sway_deg)), [x, 0, 1]))
        sides.append("front")
    n_turn = 60
    for k, a in enumerate(np.linspace(0, np.pi, n_turn + 2)[1:-1]):
        poses.append(cam(base + turn_sign * a, [10 + np.sin(a), 1 - np.cos(a), 1]))
        sides.append("front" if k < n_turn // 2 else "back")
    for x in np.linspace(10, 0, 150):
        poses.append(cam(base + turn_sign * np.pi + np.radians(rng.normal(0, sway_deg)), [x, 2, 1]))
        sides.append("back")
    return poses, sides


@pytest.mark.parametrize("turn_sign, tilt_deg, sway_deg", [(1, 0, 0), (-1, 0, 0), (1, 20, 3), (-1, -10, 3)])
def test_the_side_changes_half_way_round_the_u_turn(turn_sign, tilt_deg, sway_deg):
    poses, truth = _drive(turn_sign, tilt_deg, sway_deg, np.random.default_rng(0))
    det = UTurnSides()
    origin, restart = poses[0], False
    got, switches = [], 0
    for T in poses:
        if restart:  # the new side's reconstruction begins: its odom frame is its first camera
            origin, restart = T, False
        got.append(det.side)
        if det.update(np.linalg.inv(origin) @ T):
            switches, restart = switches + 1, True
    assert switches == 1
    # frames labelled as the simulator labels them (half of the turn each side), within 2 frames
    first_back = got.index("back")
    assert abs(first_back - truth.index("back")) <= 2, (first_back, truth.index("back"))
    assert got[-1] == "back"
