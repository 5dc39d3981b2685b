"""Writing rosbag2 bags without a ROS installation: `BagWriter` writes a rosbag2 folder (metadata.yaml + one
MCAP file) atomically: into a hidden sibling folder, renamed into place on a successful close, so a failed
write never leaves a half-written bag. Reading is io.bags.

Errors are the typed `BagError`s of `orchard_mapping.errors`, naming the bag.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
import tempfile
from pathlib import Path
from types import TracebackType
from typing import Any, Literal

import numpy as np
from rosbags.rosbag2 import (
    CompressionFormat,
    CompressionMode,
    StoragePlugin,
    Writer,
    WriterError,
)

from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import (
    BagError,
)
from orchard_mapping.io.bags import CAMERA_INFO, IMAGE, STRING
from orchard_mapping.io.typesys import typestore

__all__ = ["BagWriter", "msg_header"]

log = logging.getLogger(__name__)

def _stamp_ns(stamp: float) -> int:
    if not math.isfinite(stamp) or stamp < 0:
        raise ValueError(f"stamp must be a finite, non-negative number of seconds, got {stamp!r}")
    return round(stamp * 1e9)


def msg_header(stamp: float, frame_id: str = "") -> Any:
    """A `std_msgs/msg/Header` for `stamp` (s), to build messages for `BagWriter.write_message`."""
    store = typestore()
    sec, nanosec = divmod(_stamp_ns(stamp), 1_000_000_000)
    return store.types["std_msgs/msg/Header"](
        stamp=store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
    )


# --------------------------------------------------------------------------- writer


class BagWriter:
    """Write a rosbag2 folder with MCAP storage, atomically.

    Use as a context manager. Every `write_*` takes `stamp` in seconds: it is
    both the bag's log time and (for the messages built here) `header.stamp`.
    A topic's connection is created on its first message; one topic, one type.

        with BagWriter(tmp_path / "row1") as bag:
            bag.write_camera_info("/camera/color/camera_info", 0.0, intr)
            bag.write_color("/camera/color/image_raw", 0.0, rgb)
    """

    def __init__(self, path: str | os.PathLike[str], overwrite: bool = False, compress: bool = False) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.compress = compress  # zstd chunk compression inside the MCAP file (readable by any MCAP reader)
        self._store = typestore()
        self._tmp: Path | None = None
        self._writer: Writer | None = None
        self._conns: dict[str, tuple[Any, str]] = {}  # topic -> (connection, msgtype)

    # -- life cycle

    def open(self) -> None:
        if self._writer is not None:
            raise BagError("writer is already open", bag=str(self.path))
        if self.path.exists() and not self.overwrite:
            raise BagError("output exists already (pass overwrite=True to replace it)", bag=str(self.path))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # A sibling folder on the same file system, so the final rename is atomic.
        self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", suffix=".partial", dir=self.path.parent))
        self._writer = Writer(self._tmp / self.path.name, version=9, storage_plugin=StoragePlugin.MCAP)
        if self.compress:
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        try:
            self._writer.open()
        except BaseException:
            self.abort()
            raise

    def close(self) -> None:
        """Finish the bag and move it to `path` (replacing an existing one if `overwrite`)."""
        writer, tmp = self._require_open(), self._tmp
        assert tmp is not None
        try:
            writer.close()
        except BaseException:
            self.abort()
            raise
        self._writer = None
        if self.path.exists() or self.path.is_symlink():
            os.replace(self.path, tmp / ".replaced")
        os.replace(tmp / self.path.name, self.path)
        shutil.rmtree(tmp, ignore_errors=True)
        self._tmp = None
        log.debug("wrote bag %s (%d topics)", self.path, len(self._conns))

    def abort(self) -> None:
        """Drop everything written so far; `path` is left untouched."""
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.abort()
            self._writer = None
        if self._tmp is not None:
            shutil.rmtree(self._tmp, ignore_errors=True)
            self._tmp = None

    def __enter__(self) -> BagWriter:
        self.open()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # -- writing

    @property
    def partial(self) -> Path | None:
        """The hidden sibling folder the open bag is written into (None when not open)."""
        return self._tmp

    def flush(self) -> None:
        """Put every message written so far on disk (the MCAP chunk being filled is closed and written): a
        process killed after this leaves them readable in the partial folder (io.salvage). Costs a chunk per
        flush; for a recorder of a few messages a second."""
        storage = getattr(self._require_open(), "storage", None)
        chunk = getattr(storage, "chunk", None)
        if chunk is not None and chunk.bio.tell():
            storage.close_chunk()
        bio = getattr(storage, "bio", None)
        if bio is not None:
            bio.flush()

    def write_message(self, topic: str, stamp: float, msg: Any, msgtype: str) -> None:
        """Write any registered message type (ours included); `stamp` (s) is the log time only."""
        conn = self._connection(topic, msgtype)
        try:
            data = self._store.serialize_cdr(msg, msgtype)
        except Exception as err:  # rosbags raises assorted errors for a wrongly built message
            raise BagError(f"cannot serialize {msgtype}: {err}", bag=str(self.path), topic=topic) from err
        self._write(conn, topic, stamp, data)

    def write_raw(self, topic: str, stamp: float, data: bytes, msgtype: str) -> None:
        """Write a message already serialised (CDR, as rclpy receives it with raw=True); `stamp` (s): log time."""
        self._write(self._connection(topic, msgtype), topic, stamp, data)

    def _connection(self, topic: str, msgtype: str) -> Any:
        """The topic's connection (made on its first message); BagError for an unknown type or a second type."""
        writer = self._require_open()
        if topic not in self._conns:
            if msgtype not in self._store.types:
                raise BagError(f"unknown message type {msgtype!r}", bag=str(self.path), topic=topic)
            self._conns[topic] = (writer.add_connection(topic, msgtype, typestore=self._store), msgtype)
        conn, have = self._conns[topic]
        if have != msgtype:
            raise BagError(f"topic holds {have}, cannot also write {msgtype}", bag=str(self.path), topic=topic)
        return conn

    def _write(self, conn: Any, topic: str, stamp: float, data: bytes) -> None:
        try:
            self._require_open().write(conn, _stamp_ns(stamp), data)
        except WriterError as err:
            raise BagError(f"cannot write: {err}", bag=str(self.path), topic=topic) from err

    def write_string(self, topic: str, stamp: float, text: str) -> None:
        """std_msgs/String, e.g. the "front"/"back" side labels."""
        self.write_message(topic, stamp, self._store.types[STRING](data=text), STRING)

    def write_camera_info(self, topic: str, stamp: float, intr: CameraIntrinsics) -> None:
        """sensor_msgs/CameraInfo, plumb_bob, with K, R (identity) and P filled; frame_id from `intr`."""
        t = self._store.types
        k = np.array([intr.fx, 0.0, intr.cx, 0.0, intr.fy, intr.cy, 0.0, 0.0, 1.0])
        p = np.array([intr.fx, 0.0, intr.cx, 0.0, 0.0, intr.fy, intr.cy, 0.0, 0.0, 0.0, 1.0, 0.0])
        msg = t[CAMERA_INFO](
            header=msg_header(stamp, intr.frame_id),
            height=intr.height,
            width=intr.width,
            distortion_model="plumb_bob",
            d=np.array(intr.distortion, dtype=np.float64),
            k=k,
            r=np.eye(3).reshape(-1),
            p=p,
            binning_x=0,
            binning_y=0,
            roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
        )
        self.write_message(topic, stamp, msg, CAMERA_INFO)

    def write_color(
        self,
        topic: str,
        stamp: float,
        rgb: np.ndarray,
        encoding: Literal["rgb8", "bgr8"] = "rgb8",
        frame_id: str = "camera_color_optical_frame",
    ) -> None:
        """sensor_msgs/Image from `rgb` (H, W, 3) uint8 in RGB order, stored as rgb8 or bgr8."""
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ValueError(f"colour image must be (H, W, 3) uint8, got {rgb.shape} {rgb.dtype}")
        if encoding == "rgb8":
            pixels = rgb
        elif encoding == "bgr8":
            pixels = rgb[..., ::-1]
        else:
            raise ValueError(f"colour encoding must be 'rgb8' or 'bgr8', got {encoding!r}")
        self._write_image(topic, stamp, pixels, encoding, frame_id)

    def write_depth(
        self,
        topic: str,
        stamp: float,
        depth_m: np.ndarray,
        encoding: Literal["16UC1", "32FC1"] = "16UC1",
        frame_id: str = "camera_color_optical_frame",
    ) -> None:
        """sensor_msgs/Image from `depth_m` (H, W) metres; 0, NaN, inf and negatives are stored as 0 (missing).

        16UC1 stores rounded millimetres clipped to 65535; 32FC1 stores metres.
        """
        depth = np.asarray(depth_m)
        if depth.ndim != 2:
            raise ValueError(f"depth image must be (H, W), got {depth.shape}")
        if encoding == "16UC1":
            values = np.multiply(depth, 1000.0, dtype=np.float64)  # (H, W) mm
        elif encoding == "32FC1":
            values = np.array(depth, dtype=np.float32)  # (H, W) m
        else:
            raise ValueError(f"depth encoding must be '16UC1' or '32FC1', got {encoding!r}")
        missing = ~((values > 0) & (values < np.inf))  # NaN, inf, <= 0
        if encoding == "16UC1":
            np.rint(values, out=values)
            np.minimum(values, 65535.0, out=values)
        values[missing] = 0
        pixels = values.astype("<u2" if encoding == "16UC1" else "<f4")
        self._write_image(topic, stamp, pixels, encoding, frame_id)

    def _write_image(self, topic: str, stamp: float, pixels: np.ndarray, encoding: str, frame_id: str) -> None:
        height, width = pixels.shape[:2]
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        msg = self._store.types[IMAGE](
            header=msg_header(stamp, frame_id),
            height=height,
            width=width,
            encoding=encoding,
            is_bigendian=0,
            step=data.size // height if height else 0,
            data=data,
        )
        self.write_message(topic, stamp, msg, IMAGE)

    def _require_open(self) -> Writer:
        if self._writer is None:
            raise BagError("writer is not open (use it as a context manager)", bag=str(self.path))
        return self._writer


