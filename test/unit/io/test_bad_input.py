"""The bad-input suite (issue 46), recordings and configuration: each case ends in a typed error naming the bag,
the topic, the image and the field, shown by `orchard-map run` as one line with exit code 2 and no result folder;
or in a partial result that says what was wrong (a warning naming the bag and the topic, and the flag that
inputs.json carries). Never a traceback, never a half-written folder.

Every recording is written here with the project's bag writer, 64 x 48 px, so the file runs in seconds. The cases
that need the pipeline to run (one side missing, no trunk, a row of one tree, the output folder, Ctrl-C, a second
run into a folder) are in test/integration/test_bad_input_runs.py; docs/bad_input.md lists every case, what the
user sees and its test.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import struct
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_bags import IMAGE, INTR, H, T, W, image_msg, write_rgbd
from typer.testing import CliRunner

from orchard_mapping.cli.main import app
from orchard_mapping.config import load_config
from orchard_mapping.errors import (
    BagError,
    BagFormatError,
    BagReadError,
    CalibrationError,
    EmptyBagError,
    MissingTopicError,
)
from orchard_mapping.io.bag_writer import BagWriter, msg_header
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.io.typesys import typestore
from orchard_mapping.pipeline import run

COMPRESSED = "sensor_msgs/msg/CompressedImage"


@pytest.fixture(scope="module")
def good_back(tmp_path_factory) -> Path:
    """A well-formed recording to give as the back side beside each bad front side."""
    path = tmp_path_factory.mktemp("good") / "back"
    write_rgbd(path, n=3, seed=9)
    return path


def _texture(i: int) -> np.ndarray:  # (H, W, 3) uint8, compressible (zstd chunks then hold real blocks)
    y, x = np.mgrid[:H, :W]
    return np.stack([(x * 4 + i) % 256, (y * 5) % 256, ((x + y) * 2 + 3 * i) % 256], axis=-1).astype(np.uint8)


def _frames(bag: BagWriter, n: int, *, colour_topic: str = T.color, depth_topic: str = T.depth,
            depth_m: float | np.ndarray = 2.0, depth_encoding: str = "16UC1", dt: float = 0.1) -> None:
    """n colour + depth pairs at the same stamps, one every dt s from 1 s."""
    for i in range(n):
        t = 1.0 + dt * i
        bag.write_color(colour_topic, t, _texture(i))
        bag.write_depth(depth_topic, t, np.broadcast_to(np.asarray(depth_m, float), (H, W)).copy(),
                        depth_encoding)  # type: ignore[arg-type]


def _recording(path: Path, n: int = 3, *, info: bool = True, **kw) -> Path:
    with BagWriter(path) as bag:
        if info:
            bag.write_camera_info(T.camera_info, 0.0, INTR)
        _frames(bag, n, **kw)
    return path


def _mcap(folder: Path) -> Path:
    return next(folder.glob("*.mcap"))


def _middle_chunk(mcap: Path) -> tuple[int, int]:
    """(offset, length) of the middle chunk record of a closed MCAP file (from its summary)."""
    from mcap.reader import make_reader

    with open(mcap, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 3, "the recording must span several chunks"
    c = chunks[len(chunks) // 2]
    return c.chunk_start_offset, c.chunk_length


def _compressed_recording(path: Path) -> Path:
    """300 frames in zstd-compressed chunks (~1 MB of messages each): five chunks."""
    with BagWriter(path, compress=True) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        _frames(bag, 300)
    return path


# --------------------------------------------------------------------------- the bad recordings


def _empty(p: Path) -> Path:
    with BagWriter(p):
        pass
    return p


def _text_file(p: Path) -> Path:
    p = p.with_suffix(".mcap")
    p.write_text("these are my notes, not a recording\n")
    return p


def _missing(p: Path) -> Path:
    return p / "not_recorded_yet"


def _cut_before_any_message(p: Path) -> Path:
    _recording(p)
    cut = p.with_suffix(".mcap")
    cut.write_bytes(_mcap(p).read_bytes()[:40])  # the magic and the header only: no whole message
    return cut


def _corrupt_zstd_chunk(p: Path) -> Path:
    mcap = _mcap(_compressed_recording(p))
    offset, length = _middle_chunk(mcap)
    data = bytearray(mcap.read_bytes())
    # the chunk's second half read back as zeros (sectors lost on a failing card). A few bad bytes among the
    # compressed pixels would pass unseen: zstd checks no content, and our writer, unlike ros2 bag record, leaves
    # the chunk's CRC 0 (unchecked); the CRC case is the next one
    mid = offset + length // 2
    data[mid:offset + length] = bytes(offset + length - mid)
    mcap.write_bytes(bytes(data))
    return p


def _chunk_crc_mismatch(p: Path) -> Path:
    mcap = _mcap(_compressed_recording(p))
    offset, _ = _middle_chunk(mcap)
    data = bytearray(mcap.read_bytes())
    # Chunk record: opcode (1), length (8), message start and end time (8 + 8), uncompressed size (8), then the
    # CRC-32 of the uncompressed records. Our writer leaves it 0 (unchecked); ros2 bag record fills it in.
    crc_at = offset + 1 + 8 + 24
    data[crc_at:crc_at + 4] = struct.pack("<I", 0xDEADBEEF)
    mcap.write_bytes(bytes(data))
    return p


def _colour_on_other_topic(p: Path) -> Path:
    return _recording(p, colour_topic="/camera/rgb/image_color")


def _depth_on_other_topic(p: Path) -> Path:
    return _recording(p, depth_topic="/camera/depth/image_rect_raw")


def _text_on_colour_topic(p: Path) -> Path:
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_string(T.color, 1.0, "not an image")
    return p


def _mono8(p: Path) -> Path:
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_message(T.color, 1.0, image_msg(1.0, W, H, "mono8", W, _texture(0)[..., 0]), IMAGE)
        bag.write_depth(T.depth, 1.0, np.full((H, W), 2.0))
    return p


def _compressed_colour(p: Path) -> Path:
    ok, jpeg = cv2.imencode(".jpg", _texture(0)[..., ::-1])
    assert ok
    msg = typestore().types[COMPRESSED](header=msg_header(1.0, "cam"), format="jpeg",
                                        data=np.asarray(jpeg, np.uint8).reshape(-1))
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_message(T.color, 1.0, msg, COMPRESSED)
        bag.write_depth(T.depth, 1.0, np.full((H, W), 2.0))
    return p


def _no_camera_info(p: Path) -> Path:
    return _recording(p, info=False)


def _zero_camera_info(p: Path) -> Path:
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, dataclasses.replace(INTR, fx=0.0, fy=0.0, cx=0.0, cy=0.0))
        _frames(bag, 2)
    return p


def _camera_info_of_other_size(p: Path) -> Path:
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, dataclasses.replace(INTR, width=640, height=480))
        _frames(bag, 2)
    return p


def _depth_of_other_size(p: Path) -> Path:
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_color(T.color, 1.0, _texture(0))
        bag.write_depth(T.depth, 1.0, np.full((24, 32), 2.0))
    return p


def _colour_data_short(p: Path) -> Path:
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_message(T.color, 1.0, image_msg(1.0, W, H, "rgb8", 3 * W, np.zeros(3 * W * H - 5)), IMAGE)
        bag.write_depth(T.depth, 1.0, np.full((H, W), 2.0))
    return p


def _depth_all(value: float, encoding: str = "32FC1") -> Callable[[Path], Path]:
    def build(p: Path) -> Path:
        return _recording(p, depth_m=value, depth_encoding=encoding)
    return build


def _depth_16uc1_in_metres(p: Path) -> Path:
    """A driver that wrote metres into 16UC1: 1..4 where millimetres 1000..4000 belong."""
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        for i in range(2):
            bag.write_color(T.color, 1.0 + i, _texture(i))
            metres = (np.arange(H * W) % 4 + 1).astype("<u2").view(np.uint8)
            bag.write_message(T.depth, 1.0 + i, image_msg(1.0 + i, W, H, "16UC1", 2 * W, metres), IMAGE)
    return p


def _colour_only(p: Path) -> Path:
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        for i in range(3):
            bag.write_color(T.color, 1.0 + 0.1 * i, _texture(i))
    return p


def _depth_never_near_colour(p: Path) -> Path:
    with BagWriter(p) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        for i in range(3):
            bag.write_color(T.color, 1.0 + 0.1 * i, _texture(i))
            bag.write_depth(T.depth, 1.05 + 0.1 * i, np.full((H, W), 2.0))  # 50 ms off: beyond max_pair_dt_s
    return p


@dataclasses.dataclass(frozen=True)
class Case:
    build: Callable[[Path], Path]
    error: type[BagError]
    says: tuple[str, ...]  # what the message must hold besides the bag ("{topic}": the topic it names)
    topic: str | None = None  # the topic the error names (its .topic), None: none
    names_bag: bool = True


ERRORS: dict[str, Case] = {
    "empty bag": Case(_empty, EmptyBagError, ("bag holds no messages",)),
    "not a bag (a text file)": Case(_text_file, BagReadError, ("not a readable bag",)),
    "no such bag": Case(_missing, BagReadError, ("no such file or folder",)),
    "truncated MCAP, nothing before the cut": Case(_cut_before_any_message, BagReadError,
                                                   ("its end is missing", "no whole message")),
    "corrupt chunk in the middle (zstd)": Case(_corrupt_zstd_chunk, BagReadError,
                                               ("corrupt", "ZstdError", "the last whole message read was on",
                                                "at log time")),
    "corrupt chunk in the middle (CRC)": Case(_chunk_crc_mismatch, BagReadError,
                                              ("corrupt", "checksum", "the last whole message read was on")),
    "wrong colour topic name": Case(_colour_on_other_topic, MissingTopicError,
                                    ("colour topic not in bag", "topics present", "/camera/rgb/image_color"),
                                    T.color),
    "wrong depth topic name": Case(_depth_on_other_topic, MissingTopicError,
                                   ("depth topic not in bag", "topics present", "/camera/depth/image_rect_raw"),
                                   T.depth),
    "not an image on the colour topic": Case(_text_on_colour_topic, BagFormatError,
                                             ("std_msgs/msg/String", "expected sensor_msgs/msg/Image"), T.color),
    "mono8 colour": Case(_mono8, BagFormatError,
                         ("colour image 0", "field 'encoding' = 'mono8'", "supported: rgb8, bgr8"), T.color),
    "compressed colour": Case(_compressed_colour, BagFormatError,
                              (COMPRESSED, "expected sensor_msgs/msg/Image", "record the raw image topic"), T.color),
    "missing camera_info": Case(_no_camera_info, CalibrationError, ("no CameraInfo topic", "field 'k'"),
                                T.camera_info),
    "zero camera_info": Case(_zero_camera_info, CalibrationError, ("no valid fx/fy in field 'k'", "0.0"),
                             T.camera_info),
    "camera_info of another size": Case(_camera_info_of_other_size, CalibrationError,
                                        ("640x480", "fields 'width', 'height'", "64x48"), T.camera_info),
    "colour and depth of different sizes": Case(_depth_of_other_size, BagFormatError,
                                                ("depth image 0 is 32x24", "colour images are 64x48"), T.depth),
    "colour data shorter than height*step": Case(_colour_data_short, BagFormatError,
                                                 ("colour image 0", "field 'data' holds 9211 bytes",
                                                  "height*step"), T.color),
    "all depth NaN": Case(_depth_all(float("nan")), BagFormatError, ("no valid depth", "mode='rgb'"), T.depth),
    "all depth inf": Case(_depth_all(float("inf")), BagFormatError, ("no valid depth",), T.depth),
    "all depth zero": Case(_depth_all(0.0, "16UC1"), BagFormatError, ("no valid depth",), T.depth),
    "32FC1 depth in millimetres": Case(_depth_all(2000.0), BagFormatError,
                                       ("no valid depth", "2000 m at the median", "is it in millimetres?"), T.depth),
    "16UC1 depth in metres": Case(_depth_16uc1_in_metres, BagFormatError,
                                  ("no valid depth", "is it in metres"), T.depth),
    "colour without depth": Case(_colour_only, MissingTopicError, ("depth topic not in bag", T.color), T.depth),
    "depth never within max_pair_dt_s of colour": Case(_depth_never_near_colour, EmptyBagError,
                                                       ("no colour image has a depth image", "within 0.01 s"),
                                                       T.color),
}


@pytest.mark.parametrize("name", list(ERRORS))
def test_a_bad_recording_is_one_typed_error_and_leaves_no_folder(name, tmp_path, good_back):
    case = ERRORS[name]
    bag = case.build(tmp_path / "front")
    # the library: the typed error, naming the bag and the topic
    with pytest.raises(case.error) as info:
        run(bag, good_back, tmp_path / "api_out", load_config())
    err = info.value
    text = str(err)
    assert err.bag == str(bag) and f"bag {bag}" in text
    assert err.topic == case.topic and (case.topic is None or f"topic {case.topic}" in text)
    for part in case.says:
        assert part in text, (part, text)
    assert not (tmp_path / "api_out").exists()
    # the command: that one line, exit code 2, no traceback, no result folder
    out = tmp_path / "result"
    res = CliRunner().invoke(app, ["run", str(bag), str(good_back), "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert f"error: {text}" in res.output and "Traceback" not in res.output
    assert not out.exists()


def test_one_recording_given_as_both_sides_is_a_typed_error(tmp_path):
    bag = _recording(tmp_path / "front")
    out = tmp_path / "result"
    with pytest.raises(BagError, match="the front and the back bag are the same file") as info:
        run(bag, bag, out, load_config())
    assert info.value.bag == str(bag)
    res = CliRunner().invoke(app, ["run", str(bag), str(bag), "--out", str(out)])
    assert res.exit_code == 2 and "same file" in res.output and not out.exists()


# --------------------------------------------------------------------------- configuration typos


@pytest.mark.parametrize(("args", "says"), [
    (["--set", "input.topics.colour=/cam/rgb"],
     ("unknown key 'input.topics.colour'", "did you mean 'input.topics.color'?", "overrides given (--set)")),
    (["--set", "trunks.sourc=off"], ("unknown key 'trunks.sourc'", "did you mean 'trunks.source'?")),
    (["--set", "input.max_pair_dt_s=fast"], ("bad value for 'input.max_pair_dt_s'", "'fast'")),
    (["--set", "input.mode"], ("--set expects key=value", "'input.mode'")),
    (["--config", "{file}"], ("unknown key 'fusion.voxel_sise_m'", "did you mean 'fusion.voxel_size_m'?", "{file}")),
    (["--config", "{missing}"], ("configuration file not found", "{missing}")),
], ids=["--set key typo", "--set section key typo", "--set bad value", "--set without =", "file key typo",
        "no such file"])
def test_a_configuration_typo_names_the_key_and_runs_nothing(args, says, tmp_path, good_back):
    mine = tmp_path / "mine.yaml"
    mine.write_text("fusion:\n  voxel_sise_m: 0.02\n")
    fill = {"file": str(mine), "missing": str(tmp_path / "nope.yaml")}
    out = tmp_path / "result"
    res = CliRunner().invoke(app, ["run", str(good_back), "--out", str(out), *(a.format(**fill) for a in args)])
    assert res.exit_code == 2, res.output
    text = " ".join(res.output.split())  # typer's usage box wraps its lines
    for part in says:
        assert part.format(**fill) in text, (part, res.output)
    assert "Traceback" not in res.output and not out.exists()


# --------------------------------------------------------------------------- partial results, flagged


def _cut(src: Path, keep: float, dst: Path) -> Path:
    """src's MCAP file cut after `keep` of its bytes (the recorder lost power), written to dst."""
    data = src.read_bytes()
    dst.write_bytes(data[: int(len(data) * keep)])
    return dst


def _whole_messages_before(mcap: Path, cut: int) -> int:
    """Messages of the uncompressed MCAP file whose records end before byte `cut` (walked from its summary)."""
    from mcap.reader import make_reader

    data = mcap.read_bytes()
    with open(mcap, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    n = 0
    for c in chunks:
        pos = c.chunk_start_offset + 41 + len(c.compression) + 8  # the chunk's records (see _chunk_crc_mismatch)
        while pos < c.chunk_start_offset + c.chunk_length:
            opcode, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
            n += opcode == 0x05 and pos + 9 + length <= cut  # 0x05: a message
            pos += 9 + length
    return n


@pytest.mark.parametrize("form", ["rosbag2 folder", "bare zstd .mcap file"])
def test_a_truncated_recording_keeps_every_whole_message_and_says_how_many_were_lost(form, tmp_path, caplog):
    folder = form == "rosbag2 folder"
    with BagWriter(tmp_path / "whole", compress=not folder) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        _frames(bag, 150)
    written = 1 + 2 * 150  # the camera info, then a colour and a depth image per frame
    src = _mcap(tmp_path / "whole")
    size = src.stat().st_size
    cut_at = int(0.6 * size)
    if folder:  # its metadata.yaml, written when the bag was closed, still lists what the file held
        bag_path = tmp_path / "cut"
        bag_path.mkdir()
        shutil.copy(tmp_path / "whole" / "metadata.yaml", bag_path)
        _cut(src, 0.6, bag_path / src.name)
    else:
        bag_path = _cut(src, 0.6, tmp_path / "cut.mcap")
    with caplog.at_level(logging.WARNING):
        seq = read_rgbd(bag_path)
    cut = seq.notes.cut_short
    # the last colour image may have lost its depth image to the cut: that frame is dropped, and said
    assert cut is not None and seq.notes.flags in (("cut_short",), ("cut_short", "colour_without_depth"))
    n = len(seq)
    assert 50 < n < 150
    np.testing.assert_allclose(seq.stamps, [1.0 + 0.1 * i for i in range(n)], atol=1e-9)  # a prefix, in order
    np.testing.assert_array_equal(list(seq)[-1].color, _texture(n - 1))
    # the cut fell inside a chunk: the whole messages at its front are kept too, not only the whole chunks
    assert cut.from_cut_chunk > 0
    warning = next(r.getMessage() for r in caplog.records if "cut short" in r.getMessage())
    assert f"{cut.messages} whole messages read ({cut.from_cut_chunk} of them from the chunk the cut broke)" in warning
    if folder:
        assert cut.messages == _whole_messages_before(src, cut_at)  # every whole message before the cut
        assert cut.lost_messages == written - cut.messages
        assert f"{written - cut.messages} of the {written} messages its metadata.yaml lists were lost" in warning
    else:
        # the file's count was in its summary, which the cut took: unknown, and said to be
        assert cut.lost_messages is None and "how many messages were lost is unknown" in warning


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8"])
def test_rgb8_and_bgr8_colour_read_as_the_same_rgb(encoding, tmp_path):
    _, colours, _ = write_rgbd(tmp_path / "bag", n=2, color_encoding=encoding)
    for frame, rgb in zip(read_rgbd(tmp_path / "bag"), colours, strict=True):
        np.testing.assert_array_equal(frame.color, rgb)


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_depth_in_16uc1_millimetres_and_32fc1_metres_reads_as_metres(encoding, tmp_path):
    _, _, depths = write_rgbd(tmp_path / "bag", n=2, depth_encoding=encoding)
    for frame, depth in zip(read_rgbd(tmp_path / "bag"), depths, strict=True):
        assert frame.depth is not None
        assert np.abs(frame.depth - depth).max() <= 0.0005 + 1e-6  # 16UC1: to the nearest millimetre


def test_nan_inf_and_zero_depth_pixels_are_missing_depth_and_the_frame_stays(tmp_path):
    depth = np.full((H, W), 2.0)
    depth[0, :3] = [np.nan, np.inf, 0.0]
    _recording(tmp_path / "bag", n=2, depth_m=depth, depth_encoding="32FC1")
    frames = list(read_rgbd(tmp_path / "bag"))
    assert len(frames) == 2
    for f in frames:
        assert f.depth is not None and list(f.depth[0, :3]) == [0.0, 0.0, 0.0]
        assert np.all(f.depth[1:] == np.float32(2.0))


def _stamped(path: Path, colour_stamps: list[float], depth_stamps: list[float] | None = None) -> Path:
    """Colour images whose header stamps are colour_stamps, recorded in that order (log times rising, as a
    recorder writes what it receives), and depth images at depth_stamps (default: the same)."""
    depth = (np.full((H, W), 2000, "<u2")).view(np.uint8)  # 2 m in 16UC1
    with BagWriter(path) as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        for i, t in enumerate(colour_stamps):
            bag.write_message(T.color, 100.0 + 0.01 * i, image_msg(t, W, H, "rgb8", 3 * W, _texture(i)), IMAGE)
        for i, t in enumerate(colour_stamps if depth_stamps is None else depth_stamps):
            bag.write_message(T.depth, 100.0 + 0.01 * i, image_msg(t, W, H, "16UC1", 2 * W, depth), IMAGE)
    return path


def test_duplicate_stamps_keep_one_frame_per_stamp_flagged(tmp_path, caplog):
    bag = _stamped(tmp_path / "bag", [1.0, 1.1, 1.1, 1.2, 1.2, 1.3])
    with caplog.at_level(logging.WARNING):
        seq = read_rgbd(bag)
    np.testing.assert_allclose(seq.stamps, [1.0, 1.1, 1.2, 1.3])
    assert [f.color[0, 0, 2] for f in seq] == [_texture(i)[0, 0, 2] for i in (0, 1, 3, 5)]  # the first of each
    assert seq.notes.duplicate_stamps == 2 and seq.notes.flags == ("duplicate_stamps",)
    assert f"{bag}: 2 colour images on {T.color} repeat an earlier image's stamp (the first at 1.100 s)" in caplog.text


def test_out_of_order_stamps_are_sorted_and_flagged(tmp_path, caplog):
    bag = _stamped(tmp_path / "bag", [1.0, 1.2, 1.1, 1.3])
    with caplog.at_level(logging.WARNING):
        seq = read_rgbd(bag)
    np.testing.assert_allclose(seq.stamps, [1.0, 1.1, 1.2, 1.3])
    assert seq.notes.out_of_order_stamps == 1 and seq.notes.flags == ("out_of_order_stamps",)
    assert f"{bag}: 1 colour stamps on {T.color} are out of order" in caplog.text


def test_a_5_s_gap_is_said_with_its_stamps_and_flagged(tmp_path, caplog):
    stamps = [1.0 + 0.1 * i for i in range(10)] + [6.9 + 0.1 * i for i in range(10)]  # 1.9 s -> 6.9 s
    bag = _stamped(tmp_path / "bag", stamps)
    with caplog.at_level(logging.WARNING):
        seq = read_rgbd(bag)
    assert len(seq) == 20  # every frame is kept: the front end restarts after the gap
    ((before, after),) = seq.notes.gaps
    assert (before, after) == pytest.approx((1.9, 6.9)) and seq.notes.flags == ("stamp_gap",)
    assert f"{bag}: a gap of 5.0 s without frames on {T.color}, from 1.900 s to 6.900 s" in caplog.text
    # a steady recording, however slow, has no gap (the 2 Hz fixtures': 0.5 s a frame)
    assert read_rgbd(_stamped(tmp_path / "slow", [1.0 + 0.5 * i for i in range(8)])).notes.gaps == ()


def test_colour_images_without_depth_are_dropped_counted_and_flagged(tmp_path, caplog):
    bag = _stamped(tmp_path / "bag", [1.0, 1.1, 1.2, 1.3], depth_stamps=[1.0, 1.3])
    with caplog.at_level(logging.WARNING):
        seq = read_rgbd(bag)
    np.testing.assert_allclose(seq.stamps, [1.0, 1.3])
    assert seq.notes.colour_without_depth == 2 and seq.notes.flags == ("colour_without_depth",)
    assert f"{bag}: dropped 2 of 4 colour images without a depth image within 0.010 s" in caplog.text
