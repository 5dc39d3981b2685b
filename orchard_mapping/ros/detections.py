"""Trunk detections <-> orchard_mapping_msgs/TrunkDetectionArray (what the trunk detector node answers).

A mask travels cropped to the extent of its pixels (lossless: nothing of the instance lies outside it) and
comes back as the full-image boolean mask `core.detection.Detection` holds.

A detector that cannot read a request's image answers so explicitly (`refusal_msg`: image size 0, no
detections), so the odometry node does not wait for an answer that will not come (`is_refusal`)."""

from __future__ import annotations

import numpy as np

from orchard_mapping.core.detection import Detection
from orchard_mapping.core.types import ImagePatch, mask_bounds
from orchard_mapping.ros.messages import stamp_header

__all__ = ["detections_from_msg", "detections_to_msg", "is_refusal", "refusal_msg"]


def detections_to_msg(dets: list[Detection], stamp: float, frame_id: str, width: int, height: int):
    from orchard_mapping_msgs.msg import TrunkDetection, TrunkDetectionArray

    out = TrunkDetectionArray()
    stamp_header(out.header, stamp, frame_id)
    out.image_width, out.image_height = int(width), int(height)
    for d in dets:
        m = TrunkDetection()
        m.class_id, m.score = int(d.class_id), float(d.score)
        m.box = np.asarray(d.box, np.float32)
        mask = np.asarray(d.mask, bool)
        crop = ImagePatch.crop(mask, mask_bounds(mask))
        if crop.data.size:
            m.mask_x, m.mask_y = crop.col0, crop.row0
            m.mask_height, m.mask_width = crop.data.shape
            m.mask = crop.data.astype(np.uint8).tobytes()
        out.detections.append(m)
    return out


def detections_from_msg(msg) -> list[Detection]:
    """The detections of a TrunkDetectionArray, each with its full-image (H, W) bool mask."""
    h, w = int(msg.image_height), int(msg.image_width)
    dets = []
    for m in msg.detections:
        mask = np.zeros((h, w), bool)
        if m.mask_width and m.mask_height:
            crop = np.frombuffer(memoryview(m.mask), np.uint8).reshape(m.mask_height, m.mask_width)
            mask[m.mask_y:m.mask_y + m.mask_height, m.mask_x:m.mask_x + m.mask_width] = crop > 0
        dets.append(Detection(int(m.class_id), float(m.score), np.asarray(m.box, float), mask))
    return dets


def refusal_msg(stamp: float, frame_id: str):
    """The answer of a detector that could not read the request's image: the request's stamp, image size 0."""
    from orchard_mapping_msgs.msg import TrunkDetectionArray

    out = TrunkDetectionArray()
    stamp_header(out.header, stamp, frame_id)
    out.image_width = out.image_height = 0
    return out


def is_refusal(msg) -> bool:
    """Whether an answer says the detector could not read the image (no image has size 0)."""
    return int(msg.image_width) == 0 and int(msg.image_height) == 0
