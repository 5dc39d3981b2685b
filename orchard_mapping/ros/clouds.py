"""Coloured clouds <-> sensor_msgs/PointCloud2 (fields x y z float32 and rgb, the packed-colour convention
RViz, Foxglove and PCL read: 0x00RRGGBB stored in a float32 field)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from orchard_mapping.ros.messages import stamp_header

__all__ = ["cloud_from_msg", "cloud_to_msg"]

_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<u4")])  # 16 B per point


def cloud_to_msg(points: np.ndarray, colors: np.ndarray, frame_id: str, stamp: float) -> PointCloud2:
    """points (P, 3) m in frame_id, colors (P, 3) uint8 RGB; message time `stamp` (s)."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    col = np.asarray(colors, np.uint8).reshape(-1, 3).astype(np.uint32)
    data = np.empty(len(pts), _DTYPE)
    data["x"], data["y"], data["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    data["rgb"] = (col[:, 0] << 16) | (col[:, 1] << 8) | col[:, 2]
    msg = PointCloud2()
    stamp_header(msg.header, stamp, frame_id)
    msg.height, msg.width = 1, len(pts)
    msg.fields = [PointField(name=n, offset=o, datatype=PointField.FLOAT32, count=1)
                  for n, o in (("x", 0), ("y", 4), ("z", 8), ("rgb", 12))]
    msg.is_bigendian = False
    msg.point_step, msg.row_step = _DTYPE.itemsize, _DTYPE.itemsize * len(pts)
    msg.is_dense = True
    msg.data = data.tobytes()
    return msg


def cloud_from_msg(msg) -> tuple[np.ndarray, np.ndarray]:
    """(points (P, 3) float32, colors (P, 3) uint8) of a cloud written by `cloud_to_msg`."""
    names = [f.name for f in msg.fields]
    if names[:4] != ["x", "y", "z", "rgb"] or msg.point_step != _DTYPE.itemsize:
        raise ValueError(f"expected fields x y z rgb with a 16-byte point, got {names} and {msg.point_step} B")
    data = np.frombuffer(memoryview(msg.data), _DTYPE, count=msg.width * msg.height)
    pts = np.stack([data["x"], data["y"], data["z"]], axis=1)
    rgb = data["rgb"]
    col = np.stack([(rgb >> 16) & 255, (rgb >> 8) & 255, rgb & 255], axis=1).astype(np.uint8)
    return pts, col
