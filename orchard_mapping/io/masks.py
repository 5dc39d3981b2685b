"""Instance masks on disk as a trunk "detector" (config `trunks.source: masks`).

Layout (what `orchard-map simulate` writes, docs/ground_truth.md):
  DIR/<side>/index.csv      `frame,stamp` per mask (stamp: message time, s)
  DIR/<side>/<frame:06d>.png  16-bit instance mask: 0 background, 1..9999 trunk of tree id-1,
                             10000.. fruit, 60000.. trellis post
Frames are found by stamp (the keyframe's colour stamp, within 1 ms). A frame
without a mask has no detections. Used to measure the trunk geometry without
detector errors, and to run on a user's own annotations.
"""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np

from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK, Detection, DetectorError

__all__ = ["MaskFolderDetector", "detections_from_instance_mask"]

MASK_FRUIT, MASK_POST = 10000, 60000


def detections_from_instance_mask(m: np.ndarray) -> list[Detection]:
    """Trunk and post detections (score 1) of a 16-bit instance mask (H, W)."""
    out = []
    for val in np.unique(m):
        if 1 <= val < MASK_FRUIT:
            out.append(Detection.from_mask(m == val, CLASS_TRUNK))
        elif val >= MASK_POST:
            out.append(Detection.from_mask(m == val, CLASS_POST))
    return out


class MaskFolderDetector:
    """Detections read from `root/<side>/` by frame stamp, or from `root/` itself when it holds the index
    (one folder for a bag that holds both sides: the simulator's masks/loop/)."""

    def __init__(self, root: str | Path, side: str, stamp_tol_s: float = 0.001) -> None:
        self.dir = Path(root) / side if not (Path(root) / "index.csv").is_file() else Path(root)
        index = self.dir / "index.csv"
        if not index.is_file():
            raise DetectorError(f"trunk masks: no {index} (trunks.masks_dir must hold <side>/index.csv, or "
                                "index.csv for a bag of both sides)")
        stamps, frames = [], []
        with index.open(newline="") as f:
            for i, row in enumerate(csv.DictReader(f)):
                try:
                    frames.append(int(row["frame"]))
                    stamps.append(float(row["stamp"]))
                except (KeyError, TypeError, ValueError) as err:
                    raise DetectorError(f"{index}: line {i + 2}: expected 'frame,stamp', got {row}") from err
        self.stamps = np.asarray(stamps, float)
        self.frames = np.asarray(frames, int)
        self.tol = stamp_tol_s

    def mask_at(self, stamp: float) -> np.ndarray | None:
        """The instance mask (H, W) uint16 of the frame at `stamp` (within the tolerance), None if none."""
        if not len(self.stamps):
            return None
        j = int(np.argmin(np.abs(self.stamps - stamp)))  # the mask nearest in time
        if abs(self.stamps[j] - stamp) > self.tol:
            return None
        path = self.dir / f"{self.frames[j]:06d}.png"
        m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if m is None or m.ndim != 2:
            raise DetectorError(f"instance masks: {path} is missing or not a single-channel 16-bit PNG")
        return m

    def detect_at(self, stamp: float) -> list[Detection]:
        m = self.mask_at(stamp)
        return [] if m is None else detections_from_instance_mask(m)

    def fruit_at(self, stamp: float) -> np.ndarray | None:
        """The fruit instances (H, W) int32 (0 none, k + 1 fruit k) of the frame at `stamp`, None if no mask."""
        m = self.mask_at(stamp)
        if m is None:
            return None
        m = m.astype(np.int64)
        fruit = (m >= MASK_FRUIT) & (m < MASK_POST)
        return np.where(fruit, m - MASK_FRUIT + 1, 0).astype(np.int32)
