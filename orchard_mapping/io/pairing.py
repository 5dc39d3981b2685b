"""Colour and depth images paired by stamp, message by message: one rule for a bag and for live topics.

`RGBDPairer` gives each colour image the depth image nearest in stamp within `max_dt_ns` (ties: the
earlier stamp), and waits while a nearer depth image may still come: it pairs a colour image once a depth
image with exactly its stamp, or one at least `max_dt_ns` later, has arrived, or when the stream is flushed
(the end of a recording). Markers (a side change) keep their place behind the colour images that came
before them. `read_rgbd` feeds it a bag's stamps in stamp order; the live odometry node feeds it each
message as it arrives, so a bag replayed through the node pairs as `orchard-map run` pairs it.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["DEPTH_HELD", "Marker", "Paired", "RGBDPairer", "Unpaired", "pair_stamps"]

# depth images held for pairing. A depth image serves colour images within max_pair_dt_s (10 ms) of it, so
# only the last few matter at the camera's 15-30 Hz; 64 covers two seconds of colour arriving late.
DEPTH_HELD = 64


@dataclass(frozen=True)
class Paired:
    colour: Any
    depth: Any
    colour_ns: int  # ns, the colour image's header stamp


@dataclass(frozen=True)
class Unpaired:
    """A colour image with no depth image within max_dt_ns: its frame is dropped."""

    colour: Any
    colour_ns: int  # ns
    flushed: bool  # True: at the end of the stream (no depth followed); False: a later depth came first
    depth_held_ns: tuple[int, int] | None  # ns, the oldest and newest depth stamps held then (None: none held)


@dataclass(frozen=True)
class Marker:
    item: Any  # whatever the caller queued (a side change), in order with the colour images


class RGBDPairer:
    """Streaming pairing of colour with depth images by header stamp (see the module docstring)."""

    def __init__(self, max_dt_ns: int, depth_held: int | None = DEPTH_HELD) -> None:
        if max_dt_ns <= 0:
            raise ValueError(f"max_dt_ns must be > 0, got {max_dt_ns}")
        self.max_dt_ns = int(max_dt_ns)
        self._colour: deque[tuple[int | None, Any]] = deque()  # (stamp ns, image); (None, marker item)
        self._depth: deque[tuple[int, Any]] = deque(maxlen=depth_held)  # (stamp ns, image), recent

    def add_colour(self, stamp_ns: int, image: Any) -> None:
        self._colour.append((int(stamp_ns), image))

    def add_depth(self, stamp_ns: int, image: Any) -> None:
        self._depth.append((int(stamp_ns), image))

    def add_marker(self, item: Any) -> None:
        self._colour.append((None, item))

    @property
    def waiting(self) -> int:
        """Colour images (and markers) not yet handed out."""
        return len(self._colour)

    def pop(self, flush: bool = False, hold: bool = False) -> Iterator[Paired | Unpaired | Marker]:
        """What can be decided now, in arrival order. flush: no more depth comes (every waiting colour
        image is paired or dropped). hold: colour images wait whatever came (markers still pass): the
        node holds frames until the camera's calibration arrived."""
        tol = self.max_dt_ns
        while self._colour:
            c_ns, colour = self._colour[0]
            if c_ns is None:
                self._colour.popleft()
                yield Marker(colour)
                continue
            if hold and not flush:
                return
            best: tuple[int, int, Any] | None = None  # (|dt|, depth stamp, image): the nearest, then the earlier
            later = False
            for d_ns, depth in self._depth:
                later = later or d_ns >= c_ns + tol
                dt = abs(d_ns - c_ns)
                if dt <= tol and (best is None or (dt, d_ns) < best[:2]):
                    best = (dt, d_ns, depth)
            if not (flush or later or (best is not None and best[0] == 0)):
                return
            self._colour.popleft()
            if best is None:
                held = (self._depth[0][0], self._depth[-1][0]) if self._depth else None
                yield Unpaired(colour, c_ns, flush, held)
            else:
                yield Paired(colour, best[2], c_ns)


def pair_stamps(colour_ns: np.ndarray, depth_ns: np.ndarray, max_dt_ns: int) -> np.ndarray:
    """(N,) for each colour stamp of a whole recording, the index into depth_ns (M,) of its depth partner
    under `RGBDPairer`'s rule, -1 where there is none. The stamps are fed in stamp order (a depth stamp
    before an equal colour stamp), as a camera driver publishes them."""
    c = np.asarray(colour_ns, dtype=np.int64)
    d = np.asarray(depth_ns, dtype=np.int64)
    out = np.full(c.shape, -1, dtype=np.int64)
    pairer = RGBDPairer(max_dt_ns)
    events = sorted([(int(s), 0, j) for j, s in enumerate(d)] + [(int(s), 1, i) for i, s in enumerate(c)])
    for stamp, kind, k in events:
        if kind == 0:
            pairer.add_depth(stamp, k)
        else:
            pairer.add_colour(stamp, k)
        for ev in pairer.pop():
            if isinstance(ev, Paired):
                out[ev.colour] = ev.depth
    for ev in pairer.pop(flush=True):
        if isinstance(ev, Paired):
            out[ev.colour] = ev.depth
    return out
