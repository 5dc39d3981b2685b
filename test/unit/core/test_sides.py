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


# --------------------------------------------------------------------------- a block: row after row


def _block_drive(rows: int, *, spacing: float = 3.4, distance: float = 1.25, length: float = 4.0,
                 step: float = 0.05, tilt_deg: float = 0.0, sway_deg: float = 0.0, looks: str = "left",
                 end_after_front: bool = False, rng: np.random.Generator | None = None):
    """World camera poses of a serpentine drive along `rows` rows (row k's trunks on y = k * spacing, x in
    [0, length]): row k's front side (y = y_k - distance, looking at +y), a half circle round the row end, its
    back side (y_k + distance, looking at -y), then a half circle in the headland into the same alley the other
    way round, to row k + 1's front side. looks "left": the camera looks left of the way it goes (the drive
    goes along +x on the front sides); "right": it looks right (along -x on the front sides). Each frame's
    true (row, side), half of each turn to the side before it and half to the one after."""
    rng = rng or np.random.default_rng(0)

    def cam(look_yaw: float, pos) -> np.ndarray:
        look = np.array([np.cos(look_yaw), np.sin(look_yaw), 0.0])
        R = np.column_stack([np.cross(look, [0, 0, 1.0]), [0, 0, -1.0], look])
        R = R @ Rotation.from_euler("x", -tilt_deg, degrees=True).as_matrix()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, pos
        return T

    def sway() -> float:
        return np.radians(rng.normal(0, sway_deg)) if sway_deg else 0.0

    sgn = 1.0 if looks == "left" else -1.0  # the front sides are driven along sgn * x
    x_start, x_end = (0.0, length) if sgn > 0 else (length, 0.0)
    poses, truth = [], []

    def straight(y: float, x0: float, x1: float, look_yaw: float, label) -> None:
        for x in np.arange(x0, x1, step * np.sign(x1 - x0)):
            poses.append(cam(look_yaw + sway(), [x, y, 1.0]))
            truth.append(label)

    def half_circle(centre, radius: float, a0: float, turn: float, look_of, before, after) -> None:
        n = max(6, int(round(np.pi * radius / step)))
        for k, a in enumerate(np.linspace(0.0, np.pi, n + 2)[1:-1]):
            ang = a0 + turn * a
            poses.append(cam(look_of(ang) + sway(), [centre[0] + radius * np.cos(ang), centre[1] + radius * np.sin(ang), 1.0]))
            truth.append(before if k < n // 2 else after)

    for r in range(rows):
        y = r * spacing
        straight(y - distance, x_start, x_end, np.pi / 2, (r + 1, "front"))
        if end_after_front and r == rows - 1:
            break
        # round the row end: the camera keeps looking at the centre of the turn (the row end)
        half_circle((x_end, y), distance, -np.pi / 2, sgn, lambda a: a + np.pi, (r + 1, "front"), (r + 1, "back"))
        straight(y + distance, x_end, x_start, -np.pi / 2, (r + 1, "back"))
        if r == rows - 1:
            break
        # into the same alley the other way round: the camera looks out of the turn, away from its centre
        half_circle((x_start, y + spacing / 2), spacing / 2 - distance, -np.pi / 2, -sgn,
                    lambda a: a, (r + 1, "back"), (r + 2, "front"))
    return poses, truth


def _split(poses):
    """(row, side) per frame by UTurnSides, each pose given in its side's odom frame (a side's reconstruction
    starts at its first camera), and the turns it read."""
    det = UTurnSides()
    origin, got = None, []
    for T in poses:
        origin = T if origin is None else origin
        got.append((det.row, det.side))
        if det.update(np.linalg.inv(origin) @ T):
            origin = None
    return got, det.turns


def _changes(labels):
    return [i for i in range(1, len(labels)) if labels[i] != labels[i - 1]]


@pytest.mark.parametrize("looks, tilt_deg, sway_deg", [("left", 0, 0), ("right", 0, 0), ("left", 20, 2),
                                                        ("right", -10, 2)])
def test_a_block_drive_is_cut_into_rows_and_sides_at_its_turns(looks, tilt_deg, sway_deg):
    poses, truth = _block_drive(3, looks=looks, tilt_deg=tilt_deg, sway_deg=sway_deg)
    got, turns = _split(poses)
    # every pass named as driven: rows 1-3, each its front side then its back side
    order = [got[0]] + [got[i] for i in _changes(got)]
    assert order == [(1, "front"), (1, "back"), (2, "front"), (2, "back"), (3, "front"), (3, "back")]
    # and cut half way round each turn, within 3 frames of the truth (2.3 deg a frame round a row end: the sway
    # drawn afresh each frame moves the cut by a frame or two)
    assert len(_changes(got)) == len(_changes(truth)) == 5
    for g, t in zip(_changes(got), _changes(truth), strict=True):
        assert abs(g - t) <= 3, (g, t)
    # the turns round a row end went towards the row, those into the next row away from it
    assert [t.next_row for t in turns] == [False, True, False, True, False]
    assert all(t.back_m < -0.8 for t in turns if not t.next_row)
    assert all(t.back_m > 0.3 for t in turns if t.next_row)


def test_a_row_driven_along_one_side_only_ends_the_drive_on_its_front():
    poses, truth = _block_drive(2, end_after_front=True)
    got, turns = _split(poses)
    assert got[-1] == (2, "front") and [t.next_row for t in turns] == [False, True]


def test_a_camera_swung_the_other_way_round_the_row_end_still_goes_to_the_back_side():
    """A hand-held camera may be turned either way while its carrier walks round the row end: where the camera
    went (across the row it filmed) tells the side, not which way it turned (test above: `turn_sign` -1)."""
    poses, _ = _drive(-1, 0, 0, np.random.default_rng(0))
    got, turns = _split(poses)
    assert got[-1] == (1, "back") and len(turns) == 1 and not turns[0].next_row


def test_the_splitter_says_the_row():
    from orchard_mapping.core.sides import SideSplitter

    poses, truth = _block_drive(2)
    split = SideSplitter("trajectory")
    origin, got = None, []
    for T in poses:
        origin = T if origin is None else origin
        got.append((split.row(), split.side()))
        if split.after_pose(np.linalg.inv(origin) @ T):
            origin = None
    assert got[0] == (1, "front") and got[-1] == (2, "back") and len(split.turns()) == 3
    assert SideSplitter("topic", default_side="front").row() == 1


def test_after_a_rows_second_side_every_turn_leads_to_the_next_row():
    """A turn measured badly (its tracking lost part of the way: no move away from the row seen) after a row's
    back side still starts the next row: a drive goes along each side of a row once."""
    poses, _ = _block_drive(2)
    got, turns = _split(poses)
    assert turns[1].next_row
    det = UTurnSides()
    det.side = "back"  # on row 1's back side
    R = poses[0][:3, :3]
    for a in np.radians(np.arange(0, 181, 5)):  # a turn on the spot: the camera never moves
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([0, 0, a]).as_matrix() @ R
        if det.update(T):
            break
    assert (det.row, det.side) == (2, "front") and abs(det.turns[0].back_m) < 1e-9


def test_a_side_begun_half_way_round_a_turn_does_not_end_before_the_turn_is_over():
    """Sway drawn afresh at every frame (2 deg) over ten rows: a side begins ~90 deg off its reference, and a
    frame's sway once took it past 90 again two frames after the cut, ending the side at once; the rest of the
    turn must be over (the heading back within start_deg of the side's) before a side can end."""
    rows = 10
    poses, truth = _block_drive(rows, sway_deg=2, rng=np.random.default_rng(1))
    got, turns = _split(poses)
    assert [got[0]] + [got[i] for i in _changes(got)] == [(r, s) for r in range(1, rows + 1) for s in ("front", "back")]
    assert max(abs(g - t) for g, t in zip(_changes(got), _changes(truth), strict=True)) <= 3
