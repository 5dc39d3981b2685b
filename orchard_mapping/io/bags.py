"""Reading rosbag2 / MCAP bags without a ROS installation (writing them: io.bag_writer).

- `read_rgbd` turns a recording (rosbag2 folder or bare `.mcap` file) into a
  lazy sequence of `RGBDFrame`s.
- `describe_bag` summarises any bag for `orchard-map inspect`.

Errors are the typed `BagError`s of `orchard_mapping.errors`; each names the
bag, the topic and, where it applies, the message field.
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
from collections import Counter
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml

try:
    from compression import zstd  # Python 3.14; rosbags decompresses MCAP chunks with it (or its backport)
except ImportError:
    from backports import zstd
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Reader1Error
from rosbags.rosbag2 import (
    ReaderError as Reader2Error,
)

from orchard_mapping.config import TopicsConfig
from orchard_mapping.core.types import CameraIntrinsics, RGBDFrame
from orchard_mapping.errors import (
    BagFormatError,
    BagReadError,
    CalibrationError,
    EmptyBagError,
    MissingTopicError,
)
from orchard_mapping.io.pairing import pair_stamps
from orchard_mapping.io.salvage import Salvaged, salvaged_before, salvaged_copy
from orchard_mapping.io.typesys import typestore

__all__ = [
    "COLOR_ENCODINGS",
    "DEPTH_ENCODINGS",
    "BagSummary",
    "InputNotes",
    "RGBDSequence",
    "RawMessage",
    "camera_intrinsics",
    "decode_color",
    "decode_frame",
    "describe_bag",
    "header_ns",
    "iter_messages",
    "iter_raw",
    "read_rgbd",
]

log = logging.getLogger(__name__)

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
STRING = "std_msgs/msg/String"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"

# encoding -> (bytes per pixel, channel order of the first three channels)
COLOR_ENCODINGS: dict[str, tuple[int, str]] = {
    "rgb8": (3, "rgb"),
    "bgr8": (3, "bgr"),
    "rgba8": (4, "rgb"),
    "bgra8": (4, "bgr"),
}
# encoding -> (bytes per pixel, units per metre); 16-bit depth is millimetres
DEPTH_ENCODINGS: dict[str, tuple[int, float]] = {"16UC1": (2, 1000.0), "mono16": (2, 1000.0), "32FC1": (4, 1.0)}

_READ_ERRORS = (AnyReaderError, Reader1Error, Reader2Error, OSError, EOFError, struct.error)
MCAP_MAGIC = b"\x89MCAP0\r\n"  # an MCAP file starts and, once closed, ends with it
_DESER_ERRORS = (AnyReaderError, ValueError, IndexError, struct.error)
# A damaged chunk fails in its decompressor, which rosbags lets through: zstd's error, lz4's RuntimeError
_DECOMPRESS_ERRORS = (zstd.ZstdError, RuntimeError)
# Consecutive frames further apart than both are a gap in the recording (flagged stamp_gap): the front end
# loses track across it and restarts, leaving a seam in the side's trajectory. 1 s is 15-30 camera periods at
# a RealSense's rates; the periods bound keeps a slow recording's (a 2 Hz fixture's) own rhythm from counting.
GAP_MIN_S = 1.0
GAP_PERIODS = 5


# --------------------------------------------------------------------------- stamps


def header_ns(header: Any) -> int:
    """ns of a std_msgs/Header's stamp (rclpy's or rosbags')."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


# --------------------------------------------------------------------------- reading helpers


def _cut_mcap(path: Path) -> Path | None:
    """The MCAP file of a bag (a bare .mcap, or a rosbag2 folder holding one) whose end is missing, else None."""
    files = [path] if path.is_file() else sorted(path.glob("*.mcap")) if path.is_dir() else []
    if len(files) != 1 or files[0].suffix != ".mcap" or files[0].stat().st_size < 16:
        return None
    with open(files[0], "rb") as f:
        head = f.read(8)
        f.seek(-8, 2)
        tail = f.read(8)
    return files[0] if head == MCAP_MAGIC and tail != MCAP_MAGIC else None


@contextlib.contextmanager
def _open_reader(path: Path) -> Iterator[AnyReader]:
    """AnyReader on a rosbag2 folder or a bare storage file (.mcap, .db3; rosbag1 .bag)."""
    bag = str(path)
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except _READ_ERRORS as err:
        what = "no such file or folder" if not path.exists() else "not a readable bag"
        cut = _cut_mcap(path)
        if cut is None:
            raise BagReadError(f"{what}: {err}", bag=bag) from err
        # a recording cut short: its whole messages, from a closed copy (io.salvage)
        try:
            copy = salvaged_copy(cut)
        except BagReadError:
            raise BagReadError(f"{what}: {err} (its end is missing, and no whole message lies before the cut)",
                               bag=bag) from err
        reader = AnyReader([copy.path], default_typestore=typestore())
        reader.open()
    try:
        yield reader
    finally:
        with contextlib.suppress(Exception):
            reader.close()


def _messages(reader: AnyReader, connections: Sequence[Any], bag: str) -> Iterator[tuple[Any, int, bytes]]:
    last: tuple[str, int] | None = None  # (topic, log time ns) of the last whole message read
    try:
        for conn, log_ns, raw in reader.messages(connections=connections):
            last = (conn.topic, log_ns)
            yield conn, log_ns, raw
    except _READ_ERRORS + _DECOMPRESS_ERRORS as err:
        # where the damage lies: a corrupt chunk in the middle of a recording is found only when read
        where = (f"the last whole message read was on {last[0]} at log time {last[1] / 1e9:.3f} s" if last
                 else "no message before it could be read")
        raise BagReadError(f"bag is corrupt or truncated: {type(err).__name__}: {err}; {where}", bag=bag) from err


def _deserialize(reader: AnyReader, raw: bytes, conn: Any, bag: str) -> Any:
    try:
        return reader.deserialize(raw, conn.msgtype)
    except _DESER_ERRORS as err:
        raise BagFormatError(f"cannot decode {conn.msgtype}: {err}", bag=bag, topic=conn.topic) from err


def _check_image(msg: Any, encodings: dict[str, Any], kind: str, index: int, bag: str, topic: str) -> int:
    """Validate encoding, step and data length of a sensor_msgs/Image; return bytes per pixel."""
    if msg.encoding not in encodings:
        raise BagFormatError(
            f"{kind} image {index}: unsupported field 'encoding' = {msg.encoding!r} "
            f"(supported: {', '.join(encodings)})",
            bag=bag,
            topic=topic,
        )
    bpp = encodings[msg.encoding][0]
    if msg.step < msg.width * bpp:
        raise BagFormatError(
            f"{kind} image {index}: field 'step' = {msg.step} is less than width*{bpp} = {msg.width * bpp}",
            bag=bag,
            topic=topic,
        )
    if len(msg.data) != msg.height * msg.step:
        raise BagFormatError(
            f"{kind} image {index}: field 'data' holds {len(msg.data)} bytes, "
            f"expected height*step = {msg.height}*{msg.step} = {msg.height * msg.step}",
            bag=bag,
            topic=topic,
        )
    return bpp


def _pixels(msg: Any, bpp: int) -> np.ndarray:  # (H, W*bpp) uint8 without row padding
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8) if not isinstance(msg.data, np.ndarray) else msg.data
    return data.reshape(msg.height, msg.step)[:, : msg.width * bpp]


def _decode_color(msg: Any) -> np.ndarray:  # (H, W, 3) uint8 RGB
    bpp, order = COLOR_ENCODINGS[msg.encoding]
    px = _pixels(msg, bpp).reshape(msg.height, msg.width, bpp)
    rgb = px[..., 2::-1] if order == "bgr" else px[..., :3]
    return np.array(rgb, dtype=np.uint8, order="C")  # own, writable copy


def _depth_m(msg: Any) -> np.ndarray:  # (H, W) float32 m as the encoding reads, unchecked
    bpp, units_per_m = DEPTH_ENCODINGS[msg.encoding]
    dtype = np.dtype("u2" if bpp == 2 else "f4").newbyteorder(">" if msg.is_bigendian else "<")
    raw = np.ascontiguousarray(_pixels(msg, bpp)).view(dtype).reshape(msg.height, msg.width)
    depth = raw.astype(np.float32)
    if units_per_m != 1.0:
        depth /= np.float32(units_per_m)  # division, so whole millimetres give the nearest float32 metres
    return depth


def _decode_depth(msg: Any, depth_min_m: float, depth_max_m: float) -> np.ndarray:  # (H, W) float32 m, 0 = missing
    depth = _depth_m(msg)
    invalid = ~np.isfinite(depth) | (depth < depth_min_m) | (depth > depth_max_m)
    depth[invalid] = 0.0
    return depth


def _topic_conns(reader: AnyReader, topic: str, msgtype: str, bag: str, what: str, required: bool = True) -> list[Any]:
    info = reader.topics.get(topic)
    if info is None:
        if not required:
            return []
        present = sorted(reader.topics)
        raise MissingTopicError(f"{what} topic not in bag; topics present: {present}", bag=bag, topic=topic)
    types = {c.msgtype for c in info.connections}
    if types != {msgtype}:
        hint = (" (compressed images are not decoded: record the raw image topic, or republish it raw with "
                "image_transport)" if COMPRESSED_IMAGE in types else "")
        raise BagFormatError(f"{what} topic holds {sorted(types)}, expected {msgtype}{hint}", bag=bag, topic=topic)
    return list(info.connections)


# --------------------------------------------------------------------------- RGB-D sequence


@dataclass(frozen=True)
class InputNotes:
    """What `read_rgbd` found wrong with a recording and worked round (each also logged as a warning naming the
    bag and the topic); `orchard-map run` writes them to inputs.json, so a result made of such a recording says so."""

    colour_without_depth: int = 0  # colour images dropped: no depth image within max_pair_dt_s
    duplicate_stamps: int = 0  # colour images dropped: an earlier one in the bag has the same stamp
    out_of_order_stamps: int = 0  # colour stamps earlier than the one before them in the bag (frames are sorted)
    gaps: tuple[tuple[float, float], ...] = ()  # s, (stamp before, stamp after) of each gap between frames
    cut_short: Salvaged | None = None  # the file ended abruptly: what was read of it and what was lost

    @property
    def flags(self) -> tuple[str, ...]:
        """One word per kind of trouble, as inputs.json lists them."""
        named = (("cut_short", self.cut_short is not None), ("stamp_gap", bool(self.gaps)),
                 ("duplicate_stamps", self.duplicate_stamps > 0), ("out_of_order_stamps", self.out_of_order_stamps > 0),
                 ("colour_without_depth", self.colour_without_depth > 0))
        return tuple(name for name, on in named if on)


class RGBDSequence:
    """The RGB-D frames of one bag, decoded lazily one colour/depth pair at a time.

    Built by `read_rgbd`, which scans the bag once and raises every format
    error before any frame is decoded; iterating re-reads the bag and decodes
    only the images of the frames it yields (in colour-stamp order).
    """

    def __init__(
        self,
        bag: str,
        topics: TopicsConfig,
        mode: Literal["rgbd", "rgb"],
        intrinsics: CameraIntrinsics,
        stamps_ns: np.ndarray,  # (N,) int64 ns, sorted
        color_index: np.ndarray,  # (N,) position of each frame's colour message on its topic
        depth_index: np.ndarray,  # (N,) position of its depth message, -1 in rgb mode
        sides: tuple[str, ...],
        depth_range_m: tuple[float, float],
        dropped: int,
        notes: InputNotes | None = None,
    ) -> None:
        self.bag = bag
        self.topics = topics
        self.mode = mode
        self.intrinsics = intrinsics
        self.stamps = stamps_ns.astype(np.float64) / 1e9  # (N,) s
        self.sides = sides
        self.dropped = dropped  # colour images without a depth partner
        self.notes = notes if notes is not None else InputNotes(colour_without_depth=dropped)
        self._color_index = color_index
        self._depth_index = depth_index
        self._depth_range_m = depth_range_m

    def __len__(self) -> int:
        return int(self.stamps.size)

    @property
    def duration(self) -> float:
        """s, from the first to the last frame."""
        return float(self.stamps[-1] - self.stamps[0]) if len(self) else 0.0

    def __repr__(self) -> str:
        return f"RGBDSequence(bag={self.bag!r}, mode={self.mode!r}, frames={len(self)}, duration={self.duration:.3f}s)"

    def __iter__(self) -> Iterator[RGBDFrame]:
        n = len(self)
        want_color = {int(c) for c in self._color_index}
        depth_refs = Counter(int(d) for d in self._depth_index if d >= 0)  # a depth image may serve several frames
        pending_color: dict[int, bytes] = {}
        pending_depth: dict[int, bytes] = {}
        next_k = 0
        with _open_reader(Path(self.bag)) as reader:
            color_conns = _topic_conns(reader, self.topics.color, IMAGE, self.bag, "colour")
            depth_conns = (
                _topic_conns(reader, self.topics.depth, IMAGE, self.bag, "depth") if self.mode == "rgbd" else []
            )
            color_ids = {c.id for c in color_conns}
            counts = {"color": 0, "depth": 0}
            for conn, _, raw in _messages(reader, color_conns + depth_conns, self.bag):
                if conn.id in color_ids:
                    i = counts["color"]
                    counts["color"] += 1
                    if i in want_color:
                        pending_color[i] = raw
                else:
                    i = counts["depth"]
                    counts["depth"] += 1
                    if depth_refs.get(i):
                        pending_depth[i] = raw
                while next_k < n:
                    ci, di = int(self._color_index[next_k]), int(self._depth_index[next_k])
                    if ci not in pending_color or (di >= 0 and di not in pending_depth):
                        break
                    yield self._frame(
                        reader, next_k, pending_color.pop(ci), pending_depth.get(di), color_conns[0], depth_conns
                    )
                    if di >= 0:
                        depth_refs[di] -= 1
                        if depth_refs[di] == 0:
                            del pending_depth[di]
                    next_k += 1
        if next_k < n:
            raise BagReadError(f"bag changed while reading: {n - next_k} of {n} frames not found", bag=self.bag)

    def _frame(
        self,
        reader: AnyReader,
        k: int,
        color_raw: bytes,
        depth_raw: bytes | None,
        color_conn: Any,
        depth_conns: list[Any],
    ) -> RGBDFrame:
        color = _decode_color(_deserialize(reader, color_raw, color_conn, self.bag))
        depth = None
        if depth_raw is not None:
            depth = _decode_depth(_deserialize(reader, depth_raw, depth_conns[0], self.bag), *self._depth_range_m)
        return RGBDFrame(
            stamp=float(self.stamps[k]),
            color=color,
            depth=depth,
            intrinsics=self.intrinsics,
            side=self.sides[k],
            index=k,
        )


def _intrinsics(msg: Any) -> CameraIntrinsics | None:
    k = np.asarray(msg.k, dtype=np.float64)
    fx, fy, cx, cy = k[0], k[4], k[2], k[5]
    if not (np.isfinite([fx, fy, cx, cy]).all() and fx > 0 and fy > 0):
        return None
    return CameraIntrinsics(
        width=int(msg.width),
        height=int(msg.height),
        fx=float(fx),
        fy=float(fy),
        cx=float(cx),
        cy=float(cy),
        distortion=tuple(float(x) for x in msg.d),
        frame_id=msg.header.frame_id or CameraIntrinsics.frame_id,
    )


def camera_intrinsics(msg: Any, width: int, height: int, source: str, topic: str) -> CameraIntrinsics:
    """The intrinsics of a sensor_msgs/CameraInfo (rclpy's or rosbags') for colour images width x height, as
    `read_rgbd` takes them from a bag; CalibrationError naming the field when unusable."""
    intr = _intrinsics(msg)
    if intr is None:
        raise CalibrationError(f"no valid fx/fy in field 'k' ({[float(x) for x in msg.k]})", bag=source, topic=topic)
    return _for_images(intr, width, height, source, topic)


def _for_images(intr: CameraIntrinsics, width: int, height: int, source: str, topic: str) -> CameraIntrinsics:
    """intr for colour images width x height: CalibrationError if the CameraInfo names another size."""
    if intr.width and intr.height and (intr.width, intr.height) != (width, height):
        raise CalibrationError(f"CameraInfo is {intr.width}x{intr.height} (fields 'width', 'height') but colour "
                               f"images are {width}x{height}", bag=source, topic=topic)
    return CameraIntrinsics(width, height, intr.fx, intr.fy, intr.cx, intr.cy, intr.distortion, intr.frame_id)


def decode_color(msg: Any, source: str = "topic", topic: str = "") -> np.ndarray:
    """(H, W, 3) uint8 RGB of a colour sensor_msgs/Image (rclpy's or rosbags'); BagFormatError when malformed."""
    _check_image(msg, COLOR_ENCODINGS, "colour", 0, source, topic)
    return _decode_color(msg)


def decode_frame(color_msg: Any, depth_msg: Any | None, intr: CameraIntrinsics, index: int, side: str,
                 depth_range_m: tuple[float, float], source: str, topics: TopicsConfig) -> RGBDFrame:
    """An RGBDFrame from a colour and an aligned depth sensor_msgs/Image (rclpy's or rosbags'), checked and
    decoded exactly as `read_rgbd` decodes a bag's (stamp: the colour image's); BagFormatError naming the
    topic and field when malformed."""
    _check_image(color_msg, COLOR_ENCODINGS, "colour", index, source, topics.color)
    depth = None
    if depth_msg is not None:
        _check_image(depth_msg, DEPTH_ENCODINGS, "depth", index, source, topics.depth)
        if (depth_msg.width, depth_msg.height) != (color_msg.width, color_msg.height):
            raise BagFormatError(f"depth image {index} is {depth_msg.width}x{depth_msg.height} but the colour "
                                 f"image is {color_msg.width}x{color_msg.height} (depth must be aligned to colour)",
                                 bag=source, topic=topics.depth)
        depth = _decode_depth(depth_msg, *depth_range_m)
    return RGBDFrame(stamp=float(np.float64(header_ns(color_msg.header)) / 1e9), color=_decode_color(color_msg),
                     depth=depth, intrinsics=intr, side=side, index=index)


def _gaps(stamps_ns: np.ndarray) -> list[tuple[float, float]]:
    """(s before, s after) of each step between the sorted frame stamps longer than GAP_MIN_S and GAP_PERIODS
    camera periods (the median step)."""
    steps = np.diff(stamps_ns)
    if steps.size == 0:
        return []
    limit = max(GAP_MIN_S * 1e9, GAP_PERIODS * float(np.median(steps)))
    return [(stamps_ns[i] / 1e9, stamps_ns[i + 1] / 1e9) for i in np.flatnonzero(steps > limit)]


def _depth_unit_hint(seen_m: list[float], encoding: str, depth_min_m: float, depth_max_m: float) -> str:
    """Why no depth was in range, where the values say: depth in the other unit than its encoding's."""
    if not seen_m:
        return ""
    median = float(np.median(seen_m))
    text = f"; its finite non-zero values, read as {encoding}, are {median:.4g} m at the median"
    if encoding == "32FC1" and median > depth_max_m:
        text += " (32FC1 depth is read as metres: is it in millimetres?)"
    elif encoding in ("16UC1", "mono16") and median < depth_min_m:
        text += f" ({encoding} depth is read as millimetres: is it in metres, or scaled?)"
    return text


def read_rgbd(
    path: str | os.PathLike[str],
    topics: TopicsConfig = TopicsConfig(),  # noqa: B008 (frozen model, safe to share)
    *,
    mode: Literal["rgbd", "rgb"] = "rgbd",
    max_pair_dt_s: float = 0.01,
    depth_min_m: float = 0.2,
    depth_max_m: float = 6.0,
) -> RGBDSequence:
    """Index the RGB-D frames of a rosbag2 folder or bare `.mcap` file.

    Scans the bag once (headers, sizes, encodings; image data is discarded),
    so every error below is raised here, before any frame is decoded:
    BagReadError (missing / unreadable path, not a bag), EmptyBagError (no
    messages, no colour messages, no colour image with a depth partner),
    MissingTopicError (colour or, in rgbd mode, depth topic absent),
    BagFormatError (unsupported encoding, wrong data length, colour/depth size
    mismatch, no valid depth anywhere in rgbd mode), CalibrationError (no
    CameraInfo with finite, positive fx/fy in field 'k', or one whose size
    differs from the colour images).

    Colour images are paired with the depth image nearest in header stamp
    within `max_pair_dt_s` (io.pairing, the rule the live node follows); unpaired colour images are dropped (one warning
    with the count). Depth outside [depth_min_m, depth_max_m] becomes 0. Side
    labels come from `topics.side` (std_msgs/String, latest at or before each
    frame's stamp, by log time); "" when the topic is absent.
    """
    if mode not in ("rgbd", "rgb"):
        raise ValueError(f"mode must be 'rgbd' or 'rgb', got {mode!r}")
    if not (max_pair_dt_s > 0 and 0 <= depth_min_m < depth_max_m):
        raise ValueError("need max_pair_dt_s > 0 and 0 <= depth_min_m < depth_max_m")
    path = Path(path)
    bag = str(path)
    with _open_reader(path) as reader:
        if reader.message_count == 0:
            raise EmptyBagError("bag holds no messages", bag=bag)
        color_conns = _topic_conns(reader, topics.color, IMAGE, bag, "colour")
        if not any(c.msgcount for c in color_conns):
            raise EmptyBagError("no messages on the colour topic", bag=bag, topic=topics.color)
        depth_conns = _topic_conns(reader, topics.depth, IMAGE, bag, "depth") if mode == "rgbd" else []
        if topics.camera_info not in reader.topics:
            raise CalibrationError(
                f"no CameraInfo topic, so field 'k' (intrinsics) is unavailable; "
                f"topics present: {sorted(reader.topics)}",
                bag=bag,
                topic=topics.camera_info,
            )
        info_conns = _topic_conns(reader, topics.camera_info, CAMERA_INFO, bag, "camera info")
        side_conns = _topic_conns(reader, topics.side, STRING, bag, "side", required=False)
        groups = (("c", color_conns), ("d", depth_conns), ("i", info_conns), ("s", side_conns))
        by_id = {c.id: kind for kind, conns in groups for c in conns}
        wanted = [c for _, conns in groups for c in conns]

        color_ns: list[int] = []
        depth_ns: list[int] = []
        side_ns: list[int] = []
        side_text: list[str] = []
        color_size: tuple[int, int] | None = None
        intr: CameraIntrinsics | None = None
        bad_k: str | None = None
        n_info = 0
        depth_ok = False
        depth_seen: list[float] = []
        depth_encoding = ""  # m, median of each image's finite non-zero depth while none is in range
        for conn, log_ns, raw in _messages(reader, wanted, bag):
            kind = by_id[conn.id]
            if kind == "s":
                side_ns.append(log_ns)
                side_text.append(str(_deserialize(reader, raw, conn, bag).data).strip())
            elif kind == "i":
                n_info += 1
                if intr is None:
                    msg = _deserialize(reader, raw, conn, bag)
                    intr = _intrinsics(msg)
                    if intr is None and bad_k is None:
                        bad_k = f"k = {[float(x) for x in msg.k]}"
            elif kind == "c":
                msg = _deserialize(reader, raw, conn, bag)
                _check_image(msg, COLOR_ENCODINGS, "colour", len(color_ns), bag, conn.topic)
                size = (int(msg.width), int(msg.height))
                if color_size is None:
                    color_size = size
                elif size != color_size:
                    raise BagFormatError(
                        f"colour image {len(color_ns)} is {size[0]}x{size[1]}, "
                        f"earlier ones {color_size[0]}x{color_size[1]}",
                        bag=bag,
                        topic=conn.topic,
                    )
                color_ns.append(header_ns(msg.header))
            else:
                msg = _deserialize(reader, raw, conn, bag)
                _check_image(msg, DEPTH_ENCODINGS, "depth", len(depth_ns), bag, conn.topic)
                depth_encoding = msg.encoding
                if color_size is not None and (msg.width, msg.height) != color_size:
                    raise BagFormatError(
                        f"depth image {len(depth_ns)} is {msg.width}x{msg.height} but colour images are "
                        f"{color_size[0]}x{color_size[1]} (depth must be aligned to colour)",
                        bag=bag,
                        topic=conn.topic,
                    )
                if not depth_ok:
                    metres = _depth_m(msg)
                    depth_ok = bool(np.any((metres >= depth_min_m) & (metres <= depth_max_m)))
                    read = metres[np.isfinite(metres) & (metres > 0)]
                    if read.size:
                        depth_seen.append(float(np.median(read)))
                depth_ns.append(header_ns(msg.header))

    if not color_ns:
        raise EmptyBagError("no messages on the colour topic", bag=bag, topic=topics.color)
    assert color_size is not None
    if intr is None:
        detail = f"no valid fx/fy in field 'k' ({bad_k})" if bad_k else "field 'k' unavailable"
        raise CalibrationError(
            f"no usable CameraInfo among {n_info} messages: {detail}", bag=bag, topic=topics.camera_info
        )
    intr = _for_images(intr, color_size[0], color_size[1], bag, topics.camera_info)
    if mode == "rgbd":
        if not depth_ns:
            raise EmptyBagError(
                "no messages on the depth topic (use mode='rgb' for colour only)", bag=bag, topic=topics.depth
            )
        if not depth_ok:
            raise BagFormatError(
                f"depth topic holds no valid depth (every pixel is 0, NaN or outside [{depth_min_m}, {depth_max_m}] m) "
                f"in all {len(depth_ns)} images{_depth_unit_hint(depth_seen, depth_encoding, depth_min_m, depth_max_m)}"
                "; use mode='rgb' for colour only",
                bag=bag,
                topic=topics.depth,
            )

    c_ns = np.asarray(color_ns, dtype=np.int64)  # (Nc,) in bag order
    if np.any(np.diff(c_ns) < 0):
        log.warning(
            "%s: %d colour stamps on %s are out of order; frames are sorted by stamp",
            bag,
            int(np.sum(np.diff(c_ns) < 0)),
            topics.color,
        )
    color_index = np.argsort(c_ns, kind="stable")  # (Nc,) a stamp's first image in the bag comes first
    c_sorted = c_ns[color_index]
    repeat = np.r_[False, np.diff(c_sorted) == 0]  # (Nc,) an image whose stamp an earlier one has
    duplicates = int(np.sum(repeat))
    if duplicates:
        # the same frame written twice (a recorder's retry, two drivers on one topic): one frame per stamp,
        # or the front end would be handed a step of 0 s
        log.warning("%s: %d colour images on %s repeat an earlier image's stamp (the first at %.3f s); the "
                    "repeats are dropped", bag, duplicates, topics.color, c_sorted[repeat][0] / 1e9)
        color_index, c_sorted = color_index[~repeat], c_sorted[~repeat]
    if mode == "rgbd":
        depth_index = pair_stamps(c_sorted, np.asarray(depth_ns, dtype=np.int64), round(max_pair_dt_s * 1e9))
        keep = depth_index >= 0
        dropped = int(np.sum(~keep))
        if dropped:
            log.warning(
                "%s: dropped %d of %d colour images without a depth image within %.3f s",
                bag,
                dropped,
                c_ns.size,
                max_pair_dt_s,
            )
        if not keep.any():
            raise EmptyBagError(
                f"no colour image has a depth image ({topics.depth}) within {max_pair_dt_s} s",
                bag=bag,
                topic=topics.color,
            )
        color_index, depth_index, c_sorted = color_index[keep], depth_index[keep], c_sorted[keep]
    else:
        depth_index = np.full(color_index.shape, -1, dtype=np.int64)
        dropped = 0

    gaps = _gaps(c_sorted)
    for before, after in gaps:
        log.warning("%s: a gap of %.1f s without frames on %s, from %.3f s to %.3f s (the camera's track may be "
                    "lost across it and restarted: a seam in the trajectory)", bag, after - before, topics.color,
                    before, after)
    cut = _cut_mcap(path)
    notes = InputNotes(colour_without_depth=dropped, duplicate_stamps=duplicates,
                       out_of_order_stamps=int(np.sum(np.diff(c_ns) < 0)), gaps=tuple(gaps),
                       cut_short=salvaged_before(cut) if cut is not None else None)

    if side_ns:
        s_ns = np.asarray(side_ns, dtype=np.int64)
        s_order = np.argsort(s_ns, kind="stable")
        latest = np.searchsorted(s_ns[s_order], c_sorted, side="right") - 1  # (N,)
        sides = tuple(side_text[s_order[i]] if i >= 0 else "" for i in latest)
    else:
        sides = ("",) * c_sorted.size

    seq = RGBDSequence(
        bag, topics, mode, intr, c_sorted, color_index, depth_index, sides, (depth_min_m, depth_max_m), dropped,
        notes,
    )
    log.info("%s: %d frames (%s), %.2f s", bag, len(seq), mode, seq.duration)
    return seq


def iter_messages(path: str | os.PathLike[str], topic: str) -> Iterator[tuple[float, Any]]:
    """Decoded messages of one topic as (log time s, message), in log-time order (any type, ours included)."""
    path = Path(path)
    bag = str(path)
    with _open_reader(path) as reader:
        info = reader.topics.get(topic)
        if info is None:
            raise MissingTopicError(f"topic not in bag; topics present: {sorted(reader.topics)}", bag=bag, topic=topic)
        for conn, log_ns, raw in _messages(reader, list(info.connections), bag):
            yield log_ns / 1e9, _deserialize(reader, raw, conn, bag)


@dataclass(frozen=True)
class RawMessage:
    """One stored message, undecoded: what a bag player publishes."""

    topic: str
    msgtype: str  # e.g. "sensor_msgs/msg/Image"
    log_time_ns: int  # ns, the bag's log time
    data: bytes  # CDR with its encapsulation header, as rclpy publishes and receives it


def iter_raw(path: str | os.PathLike[str], topics: Sequence[str] | None = None,
             start_s: float = 0.0) -> Iterator[RawMessage]:
    """The stored messages of a bag (of `topics`, None: all) in log-time order, from start_s seconds after the
    bag's first message; rosbag1 messages are converted to CDR."""
    path = Path(path)
    bag = str(path)
    with _open_reader(path) as reader:
        conns = list(reader.connections)
        if topics is not None:
            missing = sorted(set(topics) - {c.topic for c in conns})
            if missing:
                raise MissingTopicError(f"topics not in bag: {missing}; topics present: {sorted(reader.topics)}",
                                        bag=bag, topic=missing[0])
            conns = [c for c in conns if c.topic in set(topics)]
        first = reader.start_time
        from_ns = first + round(start_s * 1e9)
        ros1 = not reader.is2
        for conn, log_ns, raw in _messages(reader, conns, bag):
            if log_ns < from_ns:
                continue
            if ros1:
                try:
                    raw = reader.typestore.ros1_to_cdr(raw, conn.msgtype)
                except _DESER_ERRORS as err:
                    raise BagFormatError(f"cannot convert {conn.msgtype} to CDR: {err}", bag=bag,
                                         topic=conn.topic) from err
            yield RawMessage(conn.topic, conn.msgtype, int(log_ns), bytes(raw))


# --------------------------------------------------------------------------- summary


@dataclass(frozen=True)
class BagSummary:
    """What `orchard-map inspect` shows about a bag."""

    path: str
    storage_id: str  # "mcap", "sqlite3" or "rosbag1"
    duration_s: float  # s, first to last message (log time)
    start_s: float | None  # s, log time of the first message; None for an empty bag
    end_s: float | None  # s, log time of the last message; None for an empty bag
    size_bytes: int  # all files of the bag
    topics: tuple[tuple[str, str, int], ...]  # (name, msgtype, message count), sorted by name


def _storage_id(path: Path) -> str:
    if path.is_dir():
        with contextlib.suppress(OSError, yaml.YAMLError, KeyError, TypeError):
            meta = yaml.safe_load((path / "metadata.yaml").read_text())
            return str(meta["rosbag2_bagfile_information"]["storage_identifier"])
        return "unknown"
    return {".mcap": "mcap", ".db3": "sqlite3", ".bag": "rosbag1"}.get(path.suffix, "unknown")


def describe_bag(path: str | os.PathLike[str]) -> BagSummary:
    """Summary of any bag AnyReader can open (no message is decoded)."""
    path = Path(path)
    with _open_reader(path) as reader:
        count = reader.message_count
        start = reader.start_time if count else None
        end = reader.end_time - 1 if count else None  # rosbags' end_time is 1 ns after the last message
        topics = tuple(
            sorted((name, info.msgtype or "<mixed>", int(info.msgcount)) for name, info in reader.topics.items())
        )
    size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file()) if path.is_dir() else path.stat().st_size
    return BagSummary(
        path=str(path),
        storage_id=_storage_id(path),
        duration_s=(end - start) / 1e9 if start is not None and end is not None else 0.0,
        start_s=start / 1e9 if start is not None else None,
        end_s=end / 1e9 if end is not None else None,
        size_bytes=int(size),
        topics=topics,
    )
