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


def _placed(poses):
    """Each pose in its side's odom frame: a side's reconstruction starts at its first camera."""
    return [np.linalg.inv(poses[0]) @ T for T in poses]


def test_the_splitter_follows_the_u_turn_without_labels_and_ignores_labels_on_trajectory():
    from orchard_mapping.core.sides import SideSplitter

    poses, truth = _drive(1, 0, 0, np.random.default_rng(0))
    for source in ("auto", "trajectory"):
        split = SideSplitter(source)
        if source == "trajectory":
            assert split.on_label("back") is False  # labels do not tell the side on this source
        got, origin, ends = [], poses[0], 0
        for T in poses:
            got.append(split.side())
            if split.after_pose(np.linalg.inv(origin) @ T):
                ends += 1
                origin = None
            if origin is None:
                origin = T
        assert ends == 1 and got[0] == "front" and got[-1] == "back"
        assert abs(got.index("back") - truth.index("back")) <= 2


def test_the_splitter_reads_labels_on_topic_and_a_label_change_ends_the_side():
    from orchard_mapping.core.sides import SIDE_END, SideSplitter

    split = SideSplitter("topic")
    assert split.side() == ""  # nothing names the side yet
    assert split.on_label("front") is True
    assert split.side() == "front"
    assert split.after_pose(np.eye(4)) is False  # poses never end a labelled side
    assert split.on_label("front") is False  # the same side again: it goes on
    assert split.on_label("back") is True and split.side() == "back"
    assert split.on_label(SIDE_END) is True and split.side() == ""
    assert SideSplitter("topic", default_side="back").side() == "back"
    with pytest.raises(ValueError, match="side label"):
        split.on_label("left")
