"""The run's inputs: the sides opened from the bags (`open_sides`), the frames of one side, and where a side's
keyframe images wait for fusion (read again from the bag, or spooled to disk as they come). Also what every
stage is handed: the progress callback and the run's `Timings`."""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import numpy as np

from orchard_mapping.config import OrchardConfig
from orchard_mapping.core.types import RGBDFrame
from orchard_mapping.errors import BagError, BagFormatError
from orchard_mapping.io.bags import RGBDSequence, read_rgbd

Progress = Callable[[str, int, int], None]


SIDES = ("front", "back")


@dataclass
class Timings:
    stages: dict[str, float] = field(default_factory=dict)  # s per stage
    frames: int = 0
    recording_duration_s: float = 0.0
    # s, the run's wall clock (stages overlap: the detector's thread, the trunk worker); None until it is over
    wall_s: float | None = None
    merge_steps: dict[str, float] = field(default_factory=dict)  # s per step of the `merge` stage

    def add(self, stage: str, seconds: float) -> None:
        self.stages[stage] = self.stages.get(stage, 0.0) + seconds


DRIVE = "drive"  # open_sides' key for one bag whose sides come from the camera's trajectory


def open_sides(front: Path, back: Path | None, cfg: OrchardConfig) -> dict[str, RGBDSequence]:
    """Two bags (front, back), or one bag whose side topic labels the frames, or (key DRIVE) one bag whose
    sides the camera's U-turn tells (input.side_source)."""
    inp = cfg.input
    kw = dict(mode=inp.mode, max_pair_dt_s=inp.max_pair_dt_s, depth_min_m=inp.depth_min_m, depth_max_m=inp.depth_max_m)
    if back is not None:
        if Path(front).resolve() == Path(back).resolve():
            raise BagError("the front and the back bag are the same file: a merge needs one recording of "
                           "each side of the row", bag=str(back))
        seqs = {"front": read_rgbd(front, inp.topics, **kw), "back": read_rgbd(back, inp.topics, **kw)}
        if np.array_equal(seqs["front"].stamps, seqs["back"].stamps):
            # a copy of one recording: merged with itself, a side would be mirrored onto the other
            raise BagError(f"the front and the back bag hold the same recording (the same "
                           f"{len(seqs['front'].stamps)} frame stamps as {front}): a merge needs one "
                           "recording of each side of the row", bag=str(back))
        return seqs
    seq = read_rgbd(front, inp.topics, **kw)
    labels = set(seq.sides) - {""}
    if inp.side_source == "trajectory" or (inp.side_source == "auto" and not labels):
        return {DRIVE: seq}  # the sides come from the camera's U-turn (reconstruct_drive)
    if not labels:
        raise BagFormatError("a single bag needs the side topic to tell front from back (input.side_source: "
                             "topic); no labels found", bag=str(front), topic=inp.topics.side)
    return {side: seq for side in SIDES if side in labels}


def side_mask(seq: RGBDSequence, side: str) -> np.ndarray:
    """(N,) bool: the frames of a single-bag recording labelled `side` by the side topic."""
    return np.asarray(seq.sides, dtype=str) == side


def frames_of(seq: RGBDSequence, side: str, labelled: bool) -> Iterator[RGBDFrame]:
    for f in seq:
        if not labelled or seq.sides[f.index] == side:
            yield f


class KeyframeImages(Protocol):
    """Where a side's keyframe images wait for fusion, which runs after bundle adjustment."""

    def keep(self, frame: RGBDFrame) -> None:
        """Called with each frame the front end makes a keyframe of, as it is made."""

    def frames(self, frame_index: list[int]) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        """(frame index, depth (H, W) float32 m, colour (H, W, 3) uint8) of these frames (ascending), in order."""

    def close(self) -> None:
        """Let go of what is kept."""


class BagKeyframeImages:
    """Offline: fusion reads the keyframes' images from the bag again (a second pass); nothing is kept."""

    def __init__(self, seq: RGBDSequence, side: str, labelled: bool) -> None:
        self.seq, self.side, self.labelled = seq, side, labelled

    def keep(self, frame: RGBDFrame) -> None:
        pass

    def frames(self, frame_index: list[int]) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        want = set(frame_index)
        for f in frames_of(self.seq, self.side, self.labelled):
            if f.index in want and f.depth is not None:
                yield f.index, f.depth, f.color

    def close(self) -> None:
        pass


SPOOL_PREFIX = "orchard-keyframes-"


def process_alive(pid: int) -> bool:
    """Whether a process of this id runs (one of another user counts as running)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def reap_spools(root: str | Path) -> list[Path]:
    """Remove the keyframe spool folders under `root` whose process is no longer running (a process killed
    before it let go of its spool leaves it behind); the folders removed."""
    gone = []
    for d in Path(root).glob(f"{SPOOL_PREFIX}*-*"):
        pid = d.name[len(SPOOL_PREFIX):].split("-", 1)[0]
        if d.is_dir() and not d.is_symlink() and pid.isdigit() and not process_alive(int(pid)):
            shutil.rmtree(d, ignore_errors=True)
            gone.append(d)
    return gone


class SpooledKeyframeImages:
    """Live: each keyframe's depth and colour are written to a temporary folder as the keyframe is made
    (~2 MB at 640x480, a few keyframes per second) and read back, unchanged, for fusion: memory does not
    grow with the row, and fusion sees exactly what a second pass over the bag would give.

    The folder is named after the process that made it (`orchard-keyframes-<pid>-...`). Under a folder the
    caller names (`root`: the live graph's scratch folder), a new spool first removes the folders of processes
    no longer running: a node killed mid-row and started again leaves nothing behind. (In the system's
    temporary folder, which other machines' processes may share, nothing is removed.)"""

    def __init__(self, root: str | Path | None = None) -> None:
        if root is not None:
            Path(root).mkdir(parents=True, exist_ok=True)
            reap_spools(root)
        self.dir = Path(tempfile.mkdtemp(prefix=f"{SPOOL_PREFIX}{os.getpid()}-", dir=root))

    def _paths(self, index: int) -> tuple[Path, Path]:
        return self.dir / f"{index:08d}_depth.npy", self.dir / f"{index:08d}_color.npy"

    def keep(self, frame: RGBDFrame) -> None:
        if frame.depth is None:
            return
        depth, color = self._paths(frame.index)
        np.save(depth, np.asarray(frame.depth, np.float32))
        np.save(color, np.asarray(frame.color, np.uint8))

    def frames(self, frame_index: list[int]) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
        for i in frame_index:
            depth, color = self._paths(i)
            if depth.is_file():
                yield i, np.load(depth), np.load(color)

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)
