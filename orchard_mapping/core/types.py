"""Typed value objects shared by every layer (frames and units in field comments)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of the colour camera (depth is aligned to colour)."""

    width: int  # px
    height: int  # px
    fx: float  # px
    fy: float  # px
    cx: float  # px
    cy: float  # px
    distortion: tuple[float, ...] = ()  # plumb_bob k1 k2 t1 t2 k3, empty = none
    frame_id: str = "camera_color_optical_frame"

    @property
    def K(self) -> np.ndarray:  # (3, 3)
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class RGBDFrame:
    """One colour image with its aligned depth, in the camera optical frame (REP-103)."""

    stamp: float  # s, message time of the colour image
    color: np.ndarray  # (H, W, 3) uint8, RGB order
    depth: np.ndarray | None  # (H, W) float32 metres, 0 = missing; None in RGB-only mode
    intrinsics: CameraIntrinsics
    side: str = ""  # "front" / "back" where known, else ""
    index: int = 0  # position in its stream


@dataclass(frozen=True)
class Pose:
    """Rigid pose T_parent_child as rotation + translation."""

    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,) metres

    @staticmethod
    def from_matrix(T: np.ndarray) -> "Pose":
        T = np.asarray(T, dtype=float)
        return Pose(T[:3, :3].copy(), T[:3, 3].copy())

    def matrix(self) -> np.ndarray:  # (4, 4)
        T = np.eye(4)
        T[:3, :3] = self.R
        T[:3, 3] = self.t
        return T


@dataclass(frozen=True)
class StampedTrajectory:
    """Camera poses T_odom_camera over time, as TUM stores them."""

    stamps: np.ndarray  # (N,) s
    positions: np.ndarray  # (N, 3) m, in the odom frame
    quaternions: np.ndarray  # (N, 4) qx qy qz qw
    frame_id: str = field(default="")


def mask_bounds(mask: np.ndarray, margin: int = 0) -> tuple[int, int, int, int]:
    """(r0, c0, r1, c1) px: the bounding box of a mask's pixels (H, W) grown by margin px (unclipped; all zero
    for an empty mask). With ImagePatch.crop: a mask, or what is read around it, kept without loss."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(rows) == 0:
        return 0, 0, 0, 0
    return int(rows[0]) - margin, int(cols[0]) - margin, int(rows[-1]) + 1 + margin, int(cols[-1]) + 1 + margin


@dataclass(frozen=True, eq=False)
class ImagePatch:
    """The part of an image (H, W[, C]) that a later stage reads, zero elsewhere: a keyframe's depth or mask
    kept around its trunk detections instead of whole (the streaming pipeline keeps hundreds of views).

    np.asarray(patch) gives the whole image back (built on demand, then dropped by the caller)."""

    data: np.ndarray  # (h, w[, C]) the kept rectangle
    row0: int  # px, image row of data[0]
    col0: int  # px, image column of data[:, 0]
    shape: tuple[int, ...]  # (H, W[, C]) of the whole image

    @staticmethod
    def crop(image: np.ndarray, box: tuple[int, int, int, int]) -> "ImagePatch":
        """Keep image[r0:r1, c0:c1] of box (r0, c0, r1, c1) px, clipped to the image."""
        H, W = image.shape[:2]
        r0, c0 = max(0, int(box[0])), max(0, int(box[1]))
        r1, c1 = min(H, int(box[2])), min(W, int(box[3]))
        r1, c1 = max(r0, r1), max(c0, c1)
        return ImagePatch(np.ascontiguousarray(image[r0:r1, c0:c1]), r0, c0, tuple(image.shape))

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        out = np.zeros(self.shape, self.data.dtype if dtype is None else dtype)
        h, w = self.data.shape[:2]
        out[self.row0:self.row0 + h, self.col0:self.col0 + w] = self.data
        return out

    def sum(self) -> int:
        """Of the whole image (zero outside the patch): a mask's pixel count."""
        return self.data.sum()

    @property
    def nbytes(self) -> int:
        return int(self.data.nbytes)
