"""A recording cut short (the vehicle lost power, the disk filled): every whole message before the cut, kept.

An MCAP file is written front to back and closed by a summary and a closing magic; a recorder that stops
abruptly leaves neither, and readers that start from the summary (rosbags' AnyReader) refuse the whole file
("File end magic is invalid"). The records themselves are whole up to the cut: `salvage_mcap` reads them in
order with the mcap library's stream reader (chunks decompressed, CRCs checked) until the first record the
cut broke, then the whole messages at the front of the chunk the cut broke (its records decompressed as far
as they go: a recorder's chunk holds up to a megabyte of messages), and writes the schemas, channels and
messages read into a new, closed MCAP file that any reader opens.

What was lost is said: exactly, where the bag's metadata.yaml lists the file's messages (a rosbag2 folder whose
file was cut after it was closed: a copy, a failing card); otherwise the number is unknown (the file's own
count was in the summary the cut took), and the log time of the last message kept says where the recording
stops.
"""

from __future__ import annotations

import atexit
import io
import logging
import shutil
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import yaml

from orchard_mapping.errors import BagReadError

__all__ = ["Salvaged", "salvage_mcap", "salvaged_before", "salvaged_copy"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Salvaged:
    """What salvage_mcap kept of a cut file."""

    path: Path  # the new, closed MCAP file
    messages: int  # whole messages kept
    last_log_time_ns: int | None  # the last kept message's log time
    lost_bytes: int  # bytes of the cut file after its last whole chunk or record (that chunk read as far as it goes)
    reason: str  # why reading stopped
    listed: int | None = None  # messages the bag's metadata.yaml lists for the file; None: no such list
    from_cut_chunk: int = 0  # of `messages`, those read from the front of the chunk the cut broke

    @property
    def lost_messages(self) -> int | None:
        """Messages lost, where the bag's metadata.yaml says how many the file held; None: unknown."""
        return max(0, self.listed - self.messages) if self.listed is not None else None

    def lost_text(self) -> str:
        """What was lost, in words, for the warning."""
        if self.lost_messages is not None:
            return f"{self.lost_messages} of the {self.listed} messages its metadata.yaml lists were lost"
        return "how many messages were lost is unknown (the file's count was in its summary, which the cut took)"


def _listed_messages(src: Path) -> int | None:
    """The message count the metadata.yaml of src's rosbag2 folder gives for src; None without one."""
    meta = src.parent / "metadata.yaml"
    if not meta.is_file():
        return None
    try:
        info = yaml.safe_load(meta.read_text())["rosbag2_bagfile_information"]
        for f in info.get("files") or []:
            if Path(str(f["path"])).name == src.name:
                return int(f["message_count"])
        if [Path(str(x)).name for x in info.get("relative_file_paths") or []] == [src.name]:
            return int(info["message_count"])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        return None  # a list that cannot be read is no list: the loss is estimated instead
    return None


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

    def take(record: Any) -> None:
        nonlocal n, last
        if isinstance(record, Schema):
            schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel):
            pending_channels[record.id] = record
        elif isinstance(record, Message):
            cid = channels.get(record.channel_id)
            if cid is None:
                ch = pending_channels.get(record.channel_id)
                if ch is None or (ch.schema_id and ch.schema_id not in schemas):
                    return  # a message of a channel never declared: unreadable anyway
                cid = writer.register_channel(ch.topic, ch.message_encoding,
                                              schemas.get(ch.schema_id, 0), dict(ch.metadata))
                channels[record.channel_id] = cid
            writer.add_message(cid, record.log_time, record.data, record.publish_time, record.sequence)
            n += 1
            last = record.log_time if last is None else max(last, record.log_time)

    with open(src, "rb") as f, open(dst, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="orchard_mapping salvage")
        reader = StreamReader(f, validate_crcs=True)
        try:
            for record in reader.records:
                take(record)
                if not isinstance(record, Chunk):
                    good_end = f.tell()  # after a chunk: after its records, read whole
        except Exception as err:  # the cut: a truncated record, a chunk cut short, a bad CRC (McapError, EOFError)
            reason = f"{type(err).__name__}: {err}"
        whole = n
        for record in _front_of_cut_chunk(f, good_end):
            take(record)
        writer.finish()
    if n == 0:
        dst.unlink(missing_ok=True)
        raise BagReadError(f"not a readable bag, and no whole message could be salvaged ({reason})", bag=str(src))
    return Salvaged(dst, n, last, max(0, size - good_end), reason, _listed_messages(src), n - whole)


# A chunk record: opcode, record length, message start and end time, uncompressed size, uncompressed CRC,
# then the compression's name (length-prefixed) and the records (length-prefixed)
_CHUNK_HEAD = struct.Struct("<BQQQQII")


def _front_of_cut_chunk(f: BinaryIO, start: int) -> list[Any]:
    """The whole records at the front of the chunk that starts at `start` and that the cut broke: its records
    decompressed as far as the bytes left go, up to the first record they do not hold whole. The chunk's CRC
    covers all its records, so it cannot be checked: each message is as the recorder wrote it, or the chunk's
    compression would not have decoded it (an uncompressed chunk's records are taken as they stand)."""
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema

    f.seek(start)
    head = f.read(_CHUNK_HEAD.size)
    if len(head) < _CHUNK_HEAD.size or head[0] != Opcode.CHUNK:
        return []  # the cut fell elsewhere (between chunks, in a message index): nothing more is whole
    compression = f.read(_CHUNK_HEAD.unpack(head)[-1]).decode("ascii", "replace")
    f.read(8)  # the records' length, as written: more than the cut left
    data = f.read()
    try:
        if compression == "zstd":
            import zstandard

            raw = zstandard.ZstdDecompressor().decompressobj().decompress(data)  # every whole block
        elif compression == "lz4":
            import lz4.frame

            raw = lz4.frame.LZ4FrameDecompressor().decompress(data)
        elif compression == "":
            raw = data
        else:
            return []
    except Exception:  # noqa: BLE001 - a damaged frame: nothing of it is trusted
        return []
    kinds = {Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel, Opcode.MESSAGE: Message}
    records: list[Any] = []
    pos = 0
    while pos + 9 <= len(raw):
        opcode, length = raw[pos], struct.unpack_from("<Q", raw, pos + 1)[0]
        if pos + 9 + length > len(raw):
            break  # the first record the cut broke
        kind = kinds.get(opcode)
        if kind is not None:
            body = ReadDataStream(io.BytesIO(raw[pos + 9:pos + 9 + length]))
            records.append(kind.read(body, length) if kind is Message else kind.read(body))
        pos += 9 + length
    return records


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
                    "messages read (%d of them from the chunk the cut broke), up to log time %.3f s; %s (%s)", src,
                    s.messages, s.from_cut_chunk, (s.last_log_time_ns or 0) / 1e9, s.lost_text(), s.reason)
    return _COPIES[key]


def salvaged_before(src: Path) -> Salvaged | None:
    """What salvaged_copy kept of src in this process; None if src was not salvaged."""
    return _COPIES.get(src.resolve())
