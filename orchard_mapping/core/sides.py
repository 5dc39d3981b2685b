"""Which side of the row a continuous drive is on, from the camera's heading (the U-turn at the row end).

One drive round a row (scenario `loop`: along the front side, a half circle round the row end, back
along the other side) is recorded as one stream. Without a side topic the side changes where the
camera has turned by more than `turn_deg` about the vertical from the heading it had when the side
began: half way round a U-turn, where the camera looks along the row end. The turn is read as the angle
of the camera's rotation since the side began (a turn about the vertical, whatever the camera's tilt:
measuring the heading about the camera's own "up" put the switch 4 frames late with a camera pitched
down 20 deg), from the tracked poses of the side's own reconstruction (its odom frame restarts at each
side), so the drive needs no other sensor. The next side's reference is the last one turned by half a
turn about the same axis; along the side it becomes the mean heading of the side's own frames (those within
`start_deg` of it), and the side can end only once its heading has come that near it (a side begins half
way round a turn: until that turn is over, a frame's sway must not end it again).

A drive along a whole block (scenario `block`: row after row, each row's front side, the U-turn round its
end, its back side, then a turn into the same alley the other way round to the next row's front side) turns
the same way twice in a row, but only the turn round a row's end carries the camera across the line of the
row it was looking at; the turn into the next row takes it back, away from that row. The rule tells them
apart by where the camera went between the start of the turn and half way round it, along the direction it
looked along the side (not by which way it turned: a hand-held camera may be swung either way round the row
end): a turn that moved it back from that row by more than `away_m` starts the next row (its front side);
any other is the U-turn to the other side of the same row. A drive goes along each side of a row once, so
after a row's second side every turn leads to the next row.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["SIDE_END", "SideSplitter", "Turn", "UTurnSides"]

OTHER = {"front": "back", "back": "front"}
SIDE_END = "end"  # the side topic's word for "the recording is over"


@dataclass(frozen=True)
class Turn:
    """One turn of a drive as UTurnSides read it, half way round (where the side ends)."""

    row: int  # the row the drive was on (1: the first)
    side: str  # the side that ended with the turn
    angle_deg: float  # deg turned from the side's heading when the side ended
    # m the camera moved against the direction it looked along the side, from the start of the turn to half way
    # round (negative: towards the row it looked at; round the row end that is about the camera's distance to it)
    back_m: float
    next_row: bool  # the turn leads to the next row's front side (else to the other side of this row)


@dataclass
class UTurnSides:
    """Per frame: the row and side a continuous drive is on (feed each tracked pose in order)."""

    first_side: str = "front"
    # deg: half a U-turn. A side's own heading wanders by a few degrees (a hand-held camera's sway, the
    # vehicle's steering), far below this; a turn round the row end is 180.
    turn_deg: float = 90.0
    # m: a turn that took the camera back from the row it looked at by more than this went into the next row
    # (between the start of a turn and half way round, a turn into the next row moves the camera back by
    # about half the width between the two rows' camera lines, ~0.45 m in a 3.4 m alley filmed from 1.25 m;
    # round a row end the camera moves towards the row by about its distance to it). Sway and the side's own
    # weaving move it a few cm.
    away_m: float = 0.15
    # deg: a turn begins where the heading has left the side's by this much (above a side's own sway)
    start_deg: float = 20.0
    side: str = field(init=False)
    row: int = field(init=False, default=1)
    turns: list[Turn] = field(init=False, default_factory=list)  # every turn read so far, in order
    _ref: np.ndarray | None = field(init=False, default=None)  # (3, 3) the side's reference, its odom frame
    _carried: np.ndarray = field(init=False, default_factory=lambda: np.eye(3))  # (3, 3) as carried over the turn
    _sum: np.ndarray = field(init=False, default_factory=lambda: np.zeros(3))  # rad, the side's frames vs _carried
    _n: int = field(init=False, default=0)
    _carry: np.ndarray = field(init=False, default_factory=lambda: np.eye(3))  # the reference vs its first frame
    _start: np.ndarray | None = field(init=False, default=None)  # (3,) odom: where the turn began
    # the side may end: its heading has come within start_deg of its reference. A side begins half way round a
    # turn, its heading ~90 deg off its reference; until that turn is over, a frame's sway must not end it again
    _armed: bool = field(init=False, default=True)

    def __post_init__(self) -> None:
        if self.first_side not in OTHER:
            raise ValueError(f"first_side must be front or back, got {self.first_side!r}")
        self.side = self.first_side

    def update(self, T_odom_cam: np.ndarray) -> bool:
        """A frame of the current side, placed at T_odom_cam (4, 4) in that side's odom frame: True if the
        side ends with it (frames the front end could not place, NaN, never end a side). `side` and `row` are
        then the next frame's; the caller starts that side's reconstruction with the next frame, and its poses
        (odom frame: that first camera) are what the next calls get."""
        T = np.asarray(T_odom_cam, float)
        if not np.all(np.isfinite(T)):
            return False
        R, p = T[:3, :3], T[:3, 3]
        if self._ref is None:
            self._ref = self._carried = R @ self._carry
            self._sum, self._n = np.zeros(3), 0
        turned = Rotation.from_matrix(self._ref.T @ R).as_rotvec()  # (3,) rad, body axis x angle
        angle = float(np.linalg.norm(turned))
        if angle <= np.radians(self.start_deg):
            # Along the side: its reference becomes the mean heading of its frames so far. The carried one is a
            # frame's turn off (the next side starts a frame after the one it was carried from), and over a
            # block's turns that added up until a side's heading never came near its reference again.
            self._sum += Rotation.from_matrix(self._carried.T @ R).as_rotvec()
            self._n += 1
            self._ref = self._carried @ Rotation.from_rotvec(self._sum / self._n).as_matrix()
            turned = Rotation.from_matrix(self._ref.T @ R).as_rotvec()
            angle = float(np.linalg.norm(turned))
            self._armed = True
        if self._start is None or angle <= np.radians(self.start_deg):
            self._start = p.copy()  # the last place before the turn (a side that is all turn: its first)
        if angle <= np.radians(self.turn_deg) or not self._armed:
            return False
        # where the camera went since the turn began, along the direction it looked along the side
        back_m = -float((self._ref.T @ (p - self._start))[2])
        # A drive goes along each side of a row once: after a row's second side every turn leads on to the next
        # row, whatever it measured (a turn whose tracking was lost part of the way is measured badly).
        next_row = back_m > self.away_m or self.side != self.first_side
        self.turns.append(Turn(self.row, self.side, float(np.degrees(angle)), back_m, next_row))
        half = Rotation.from_rotvec(np.pi * turned / angle).as_matrix()  # half a turn about the same axis
        self._carry = R.T @ (self._ref @ half)  # the next side's reference against its first frame (~ this one)
        self._ref = None
        self._start = None
        self._armed = False
        if next_row:
            self.row += 1
            self.side = self.first_side
        else:
            self.side = OTHER[self.side]
        return True


class SideSplitter:
    """Which side (and, along a block, which row) each frame of a stream belongs to, and where a side ends: the
    rule of input.side_source for one stream of frames, side-topic labels and tracked poses, fed in order. The
    live odometry node feeds it message by message; `orchard-map run` feeds it a drive's frames (pipeline.side).

    source "topic": the side topic's labels ("front", "back"; "end" ends the side); "trajectory": the
    camera's U-turn (UTurnSides) and labels other than "end" are ignored; "auto": the labels where a side is
    named (by the topic or by `default_side`, the node's `side` parameter), the U-turn where none is.
    """

    def __init__(self, source: str = "auto", default_side: str = "") -> None:
        if source not in ("auto", "topic", "trajectory"):
            raise ValueError(f"source must be auto, topic or trajectory, got {source!r}")
        if default_side not in ("", *OTHER):
            raise ValueError(f"default_side must be '', front or back, got {default_side!r}")
        self.source = source
        self.default_side = default_side
        self._label = ""  # the side the topic named last ("" none, or after "end")
        self._turns: UTurnSides | None = None  # the U-turn rule, once it tells the side

    def on_label(self, label: str) -> bool:
        """A side-topic message: True if the side being tracked ends here (the caller finishes it; the
        next frame starts the side `side()` then names)."""
        if label != SIDE_END and label not in OTHER:
            raise ValueError(f"side label must be front, back or {SIDE_END}, got {label!r}")
        if self.source == "trajectory" and label != SIDE_END:
            return False
        ends = label != self._label or self._turns is not None
        self._label = "" if label == SIDE_END else label
        self._turns = None
        return ends

    def side(self) -> str:
        """The side of the next frame ("" while nothing names one: source "topic" with no label and no
        default side)."""
        if self._turns is not None or self.source == "trajectory" or (
                self.source == "auto" and not (self._label or self.default_side)):
            self._turns = self._turns or UTurnSides()
            return self._turns.side
        return self._label or self.default_side

    def row(self) -> int:
        """The row of the next frame, counted from 1 in the order driven: a new one after each turn into the next
        row (core.sides.UTurnSides; labelled sides are all of row 1)."""
        return self._turns.row if self._turns is not None else 1

    def turns(self) -> list[Turn]:
        """The turns the trajectory told so far (none where labels tell the side)."""
        return list(self._turns.turns) if self._turns is not None else []

    def after_pose(self, T_odom_cam: np.ndarray) -> bool:
        """The frame just given `side()` was placed at T_odom_cam (4, 4) in its side's odom frame: True if
        its side ends with it (half way round the U-turn; only where the U-turn tells the side)."""
        return self._turns is not None and self._turns.update(T_odom_cam)
