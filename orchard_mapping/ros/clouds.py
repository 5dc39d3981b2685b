"""Coloured clouds <-> sensor_msgs/PointCloud2 (fields x y z float32 and rgb, the packed-colour convention
RViz, Foxglove and PCL read: 0x00RRGGBB stored in a float32 field)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from orchard_mapping.ros.messages import stamp_header

__all__ = ["cloud_to_msg"]

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
