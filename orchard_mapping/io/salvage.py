"""A recording cut short (the vehicle lost power, the disk filled): every whole message before the cut, kept.

An MCAP file is written front to back and closed by a summary and a closing magic; a recorder that stops
abruptly leaves neither, and readers that start from the summary (rosbags' AnyReader) refuse the whole file
("File end magic is invalid"). The records themselves are whole up to the cut: `salvage_mcap` reads them in
order with the mcap library's stream reader (chunks decompressed, CRCs checked) until the first record the
cut broke, and writes the schemas, channels and messages read into a new, closed MCAP file that any reader
opens. What was lost is said: the bytes after the last whole record.
"""

from __future__ import annotations

import atexit
import logging
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from orchard_mapping.errors import BagReadError

__all__ = ["Salvaged", "salvage_mcap", "salvaged_copy"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Salvaged:
    """What salvage_mcap kept of a cut file."""

    path: Path  # the new, closed MCAP file
    messages: int  # whole messages kept
    last_log_time_ns: int | None  # the last kept message's log time
    lost_bytes: int  # bytes of the cut file after its last whole record
    reason: str  # why reading stopped


def salvage_mcap(src: Path, dst: Path) -> Salvaged:
    """Every whole message of the MCAP file src, in order, into the new file dst; BagReadError when src is not
    an MCAP file at all (no leading magic) or holds no whole message."""
    from mcap.records import Channel, Chunk, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

    size = src.stat().st_size
    schemas: dict[int, int] = {}  # id in src -> id in dst
    channels: dict[int, int] = {}
    pending_channels: dict[int, Channel] = {}
    n, last = 0, None
    good_end, reason = 0, "the file ends"
    with open(src, "rb") as f, open(dst, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="orchard_mapping salvage")
        reader = StreamReader(f, validate_crcs=True)
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel):
                    pending_channels[record.id] = record
                elif isinstance(record, Message):
                    cid = channels.get(record.channel_id)
                    if cid is None:
                        ch = pending_channels.get(record.channel_id)
                        if ch is None or (ch.schema_id and ch.schema_id not in schemas):
                            continue  # a message of a channel never declared: unreadable anyway
                        cid = writer.register_channel(ch.topic, ch.message_encoding,
                                                      schemas.get(ch.schema_id, 0), dict(ch.metadata))
                        channels[record.channel_id] = cid
                    writer.add_message(cid, record.log_time, record.data, record.publish_time, record.sequence)
                    n += 1
                    last = record.log_time if last is None else max(last, record.log_time)
                if not isinstance(record, Chunk):
                    good_end = f.tell()
        except Exception as err:  # the cut: a truncated record, a chunk cut short, a bad CRC (McapError, EOFError)
            reason = f"{type(err).__name__}: {err}"
        writer.finish()
    if n == 0:
        dst.unlink(missing_ok=True)
        raise BagReadError(f"not a readable bag, and no whole message could be salvaged ({reason})", bag=str(src))
    return Salvaged(dst, n, last, max(0, size - good_end), reason)


_COPIES: dict[Path, Salvaged] = {}
_TMP: list[Path] = []


def _cleanup() -> None:
    for d in _TMP:
        shutil.rmtree(d, ignore_errors=True)


def salvaged_copy(src: Path) -> Salvaged:
    """The salvaged copy of the cut MCAP file src (made once per process, in a temporary folder removed at
    exit), logging what was kept and what was lost."""
    key = src.resolve()
    if key not in _COPIES:
        if not _TMP:
            atexit.register(_cleanup)
        d = Path(tempfile.mkdtemp(prefix="orchard-salvaged-"))
        _TMP.append(d)
        s = salvage_mcap(src, d / src.name)
        _COPIES[key] = s
        log.warning("%s is cut short (no summary or closing magic: the recording stopped abruptly): %d whole "
                    "messages read, up to log time %.3f s; the last %d bytes were lost (%s)", src, s.messages,
                    (s.last_log_time_ns or 0) / 1e9, s.lost_bytes, s.reason)
    return _COPIES[key]
