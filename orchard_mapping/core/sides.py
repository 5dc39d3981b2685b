"""Which side of the row a continuous drive is on, from the camera's heading (the U-turn at the row end).

One drive round a row (scenario `loop`: along the front side, a half circle round the row end, back
along the other side) is recorded as one stream. Without a side topic the side changes where the
camera has turned by more than `turn_deg` about the vertical from the heading it had when the side
began: half way round a U-turn, where the camera looks along the row end. The turn is read as the angle
of the camera's rotation since the side began (a turn about the vertical, whatever the camera's tilt:
measuring the heading about the camera's own "up" put the switch 4 frames late with a camera pitched
down 20 deg), from the tracked poses of the side's own reconstruction (its odom frame restarts at each
side), so the drive needs no other sensor. The next side's reference is the last one turned by half a
turn about the same axis.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["SIDE_END", "SideSplitter", "UTurnSides"]

OTHER = {"front": "back", "back": "front"}
SIDE_END = "end"  # the side topic's word for "the recording is over"


@dataclass
class UTurnSides:
    """Per frame: the side a continuous drive is on (feed each tracked pose in order)."""

    first_side: str = "front"
    # deg: half a U-turn. A side's own heading wanders by a few degrees (a hand-held camera's sway, the
    # vehicle's steering), far below this; a turn round the row end is 180.
    turn_deg: float = 90.0
    side: str = field(init=False)
    _ref: np.ndarray | None = field(init=False, default=None)  # (3, 3) the side's reference, its odom frame
    _carry: np.ndarray = field(init=False, default_factory=lambda: np.eye(3))  # the reference vs its first frame

    def __post_init__(self) -> None:
        if self.first_side not in OTHER:
            raise ValueError(f"first_side must be front or back, got {self.first_side!r}")
        self.side = self.first_side

    def update(self, T_odom_cam: np.ndarray) -> bool:
        """A frame of the current side, placed at T_odom_cam (4, 4) in that side's odom frame: True if the
        side ends with it (frames the front end could not place, NaN, never end a side). `side` is then
        the next frame's; the caller starts that side's reconstruction with the next frame, and its poses
        (odom frame: that first camera) are what the next calls get."""
        T = np.asarray(T_odom_cam, float)
        if not np.all(np.isfinite(T)):
            return False
        R = T[:3, :3]
        if self._ref is None:
            self._ref = R @ self._carry
        turned = Rotation.from_matrix(self._ref.T @ R).as_rotvec()  # (3,) rad, body axis x angle
        angle = float(np.linalg.norm(turned))
        if angle <= np.radians(self.turn_deg):
            return False
        half = Rotation.from_rotvec(np.pi * turned / angle).as_matrix()  # half a turn about the same axis
        self._carry = R.T @ (self._ref @ half)  # the next side's reference against its first frame (~ this one)
        self._ref = None
        self.side = OTHER[self.side]
        return True


class SideSplitter:
    """Which side each frame of a stream belongs to, and where a side ends: the rule of input.side_source
    for one stream of frames, side-topic labels and tracked poses, fed in order. The live odometry node
    feeds it message by message; `orchard-map run` feeds it a drive's frames (pipeline.side).

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

    def after_pose(self, T_odom_cam: np.ndarray) -> bool:
        """The frame just given `side()` was placed at T_odom_cam (4, 4) in its side's odom frame: True if
        its side ends with it (half way round the U-turn; only where the U-turn tells the side)."""
        return self._turns is not None and self._turns.update(T_odom_cam)
