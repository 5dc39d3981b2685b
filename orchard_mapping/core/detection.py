"""Trunk detection (paper: "Trunk Detection"): instance masks of trunks and trellis posts.

Detections come from an instance-segmentation model (the ONNX runtime below,
contract in docs/detector.md) or, to measure the geometry alone, from instance
masks on disk (the simulator's, or a user's annotations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from orchard_mapping.errors import OrchardMappingError

__all__ = ["CLASS_NAMES", "CLASS_POST", "CLASS_TRUNK", "Detection", "DetectorError"]

CLASS_TRUNK = 1
CLASS_POST = 2  # a trellis post is never a trunk (the merge may still use it as a landmark)
CLASS_NAMES = {CLASS_TRUNK: "trunk", CLASS_POST: "post"}


class DetectorError(OrchardMappingError):
    """A detector model or its input cannot be used (the message names the file and what is wrong)."""


@dataclass(frozen=True)
class Detection:
    """One instance in one colour image (pixels of that image)."""

    class_id: int  # CLASS_TRUNK or CLASS_POST
    score: float  # 0..1
    box: np.ndarray  # (4,) float px: x1 y1 x2 y2
    mask: np.ndarray  # (H, W) bool

    @staticmethod
    def from_mask(mask: np.ndarray, class_id: int, score: float = 1.0) -> "Detection":
        v, u = np.nonzero(mask)
        box = np.array([u.min(), v.min(), u.max() + 1, v.max() + 1], float) if len(u) else np.zeros(4)
        return Detection(class_id, float(score), box, np.asarray(mask, bool))
