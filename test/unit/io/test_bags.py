"""BagWriter / read_rgbd / describe_bag / iter_messages: real bags written into tmp_path and read back."""

from __future__ import annotations

import dataclasses
import logging
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from orchard_mapping.config import TopicsConfig
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import (
    BagError,
    BagFormatError,
    BagReadError,
    CalibrationError,
    EmptyBagError,
    MissingTopicError,
)
from orchard_mapping.io.bag_writer import BagWriter, msg_header
from orchard_mapping.io.bags import describe_bag, iter_messages, read_rgbd
from orchard_mapping.io.typesys import typestore

T = TopicsConfig()
W, H = 64, 48
INTR = CameraIntrinsics(W, H, 52.5, 53.25, 31.5, 23.75, (0.1, -0.02, 0.001, 0.0, 0.003), "cam_optical")
IMAGE = "sensor_msgs/msg/Image"


def rgb_image(rng: np.random.Generator) -> np.ndarray:  # (H, W, 3)
    return rng.integers(0, 256, (H, W, 3), dtype=np.uint8)


def depth_image(rng: np.random.Generator) -> np.ndarray:  # (H, W) m, all inside the default range
    return rng.uniform(0.3, 5.5, (H, W))


def write_rgbd(
    path: Path,
    n: int = 4,
    *,
    color_encoding: str = "rgb8",
    depth_encoding: str = "16UC1",
    seed: int = 0,
    dt: float = 0.1,
    depth_offset: float = 0.002,
    camera_info: bool = True,
) -> tuple[list[float], list[np.ndarray], list[np.ndarray]]:
    """n colour + depth pairs (depth 2 ms after colour); returns stamps, colours, depths written."""
    rng = np.random.default_rng(seed)
    stamps, colors, depths = [], [], []
    with BagWriter(path) as bag:
        if camera_info:
            bag.write_camera_info(T.camera_info, 0.0, INTR)
        for i in range(n):
            t = 1.0 + dt * i
            rgb, depth = rgb_image(rng), depth_image(rng)
            bag.write_color(T.color, t, rgb, color_encoding)  # type: ignore[arg-type]
            bag.write_depth(T.depth, t + depth_offset, depth, depth_encoding)  # type: ignore[arg-type]
            stamps.append(t)
            colors.append(rgb)
            depths.append(depth)
    return stamps, colors, depths


def image_msg(stamp: float, width: int, height: int, encoding: str, step: int, data: np.ndarray) -> Any:
    return typestore().types[IMAGE](
        header=msg_header(stamp, "cam"),
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=step,
        data=np.asarray(data, dtype=np.uint8).reshape(-1),
    )


def same(a: Any, b: Any) -> bool:
    """Field-wise equality of rosbags messages (classes differ between type stores), NaN == NaN."""
    if dataclasses.is_dataclass(a):
        return type(a).__msgtype__ == type(b).__msgtype__ and all(
            same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    return bool(a == b)


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8"])
def test_color_round_trip_is_bit_exact(tmp_path: Path, encoding: str) -> None:
    stamps, colors, _ = write_rgbd(tmp_path / "bag", color_encoding=encoding)
    seq = read_rgbd(tmp_path / "bag")
    frames = list(seq)
    assert len(seq) == len(frames) == 4
    np.testing.assert_allclose(seq.stamps, stamps, atol=1e-9)
    for k, (frame, rgb) in enumerate(zip(frames, colors, strict=True)):
        assert frame.index == k
        assert frame.color.dtype == np.uint8 and frame.color.shape == (H, W, 3)
        np.testing.assert_array_equal(frame.color, rgb)
        assert frame.color.flags.writeable
    assert seq.duration == pytest.approx(0.3)


def test_bgr8_is_stored_in_bgr_order(tmp_path: Path) -> None:
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = 200  # pure red
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_color(T.color, 1.0, rgb, "bgr8")
    ((_, msg),) = list(iter_messages(tmp_path / "bag", T.color))
    assert msg.encoding == "bgr8"
    assert msg.step == 3 * W
    assert tuple(msg.data[:3]) == (0, 0, 200)


def test_depth_16uc1_quantises_to_half_a_millimetre(tmp_path: Path) -> None:
    _, _, depths = write_rgbd(tmp_path / "bag", depth_encoding="16UC1")
    for frame, depth in zip(read_rgbd(tmp_path / "bag"), depths, strict=True):
        assert frame.depth is not None and frame.depth.dtype == np.float32 and frame.depth.shape == (H, W)
        assert np.abs(frame.depth - depth).max() <= 0.0005 + 1e-6  # float32 rounding on top of mm rounding


def test_depth_32fc1_is_exact(tmp_path: Path) -> None:
    _, _, depths = write_rgbd(tmp_path / "bag", depth_encoding="32FC1")
    for frame, depth in zip(read_rgbd(tmp_path / "bag"), depths, strict=True):
        assert frame.depth is not None
        np.testing.assert_array_equal(frame.depth, depth.astype(np.float32))


@pytest.mark.parametrize("encoding", ["16UC1", "32FC1"])
def test_depth_outside_range_and_invalid_values_become_zero(tmp_path: Path, encoding: str) -> None:
    depth = np.full((H, W), 2.0)
    depth[0, :4] = [0.1, 7.0, np.nan, -1.0]  # too near, too far, NaN, negative
    depth[1, 0] = 100.0  # beyond 65.535 m: clipped in 16UC1, still out of range
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.uint8))
        bag.write_depth(T.depth, 1.0, depth, encoding)  # type: ignore[arg-type]
    (frame,) = list(read_rgbd(tmp_path / "bag", depth_min_m=0.2, depth_max_m=6.0))
    assert frame.depth is not None
    assert list(frame.depth[0, :4]) == [0.0, 0.0, 0.0, 0.0]
    assert frame.depth[1, 0] == 0.0
    assert np.all(frame.depth[2:] == np.float32(2.0))


def test_camera_info_round_trips_to_equal_intrinsics(tmp_path: Path) -> None:
    write_rgbd(tmp_path / "bag", n=1)
    seq = read_rgbd(tmp_path / "bag")
    assert seq.intrinsics == INTR
    frame = next(iter(seq))
    assert frame.intrinsics == INTR
    ((_, msg),) = list(iter_messages(tmp_path / "bag", T.camera_info))
    assert msg.distortion_model == "plumb_bob"
    np.testing.assert_array_equal(msg.r, np.eye(3).reshape(-1))
    np.testing.assert_array_equal(msg.p.reshape(3, 4)[:, :3], INTR.K)


def test_first_valid_camera_info_wins(tmp_path: Path) -> None:
    bad = dataclasses.replace(INTR, fx=0.0)
    later = dataclasses.replace(INTR, fx=99.0)
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, bad)
        bag.write_camera_info(T.camera_info, 0.5, INTR)
        bag.write_camera_info(T.camera_info, 0.6, later)
        bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.uint8))
    assert read_rgbd(tmp_path / "bag", mode="rgb").intrinsics == INTR


def test_side_labels_are_the_latest_at_or_before_each_frame(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_string(T.side, 1.05, "front")
        bag.write_string(T.side, 1.2, "back")
        for t in (1.0, 1.1, 1.2, 1.3):
            bag.write_color(T.color, t, np.zeros((H, W, 3), np.uint8))
            bag.write_depth(T.depth, t, np.ones((H, W)))
    seq = read_rgbd(tmp_path / "bag")
    assert seq.sides == ("", "front", "back", "back")
    assert [f.side for f in seq] == ["", "front", "back", "back"]


def test_no_side_topic_gives_empty_labels(tmp_path: Path) -> None:
    write_rgbd(tmp_path / "bag", n=2)
    seq = read_rgbd(tmp_path / "bag")
    assert seq.sides == ("", "")
    assert all(f.side == "" for f in seq)


def test_rgb_mode_needs_no_depth(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    rgb = rgb_image(rng)
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_color(T.color, 1.0, rgb)
    (frame,) = list(read_rgbd(tmp_path / "bag", mode="rgb"))
    assert frame.depth is None
    np.testing.assert_array_equal(frame.color, rgb)


def test_one_depth_image_may_serve_two_colour_images(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_color(T.color, 1.000, np.full((H, W, 3), 1, np.uint8))
        bag.write_depth(T.depth, 1.003, np.full((H, W), 1.0))
        bag.write_color(T.color, 1.006, np.full((H, W, 3), 2, np.uint8))
    frames = list(read_rgbd(tmp_path / "bag"))
    assert [int(f.color[0, 0, 0]) for f in frames] == [1, 2]
    assert all(f.depth is not None and f.depth[0, 0] == 1.0 for f in frames)


def test_colour_without_depth_partner_is_dropped_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        for t, c in ((1.0, 1), (1.1, 2), (1.2, 3)):
            bag.write_color(T.color, t, np.full((H, W, 3), c, np.uint8))
        bag.write_depth(T.depth, 1.004, np.ones((H, W)))
        bag.write_depth(T.depth, 1.125, np.ones((H, W)))  # 25 ms from colour 2: too far
        bag.write_depth(T.depth, 1.199, np.ones((H, W)))
    with caplog.at_level(logging.WARNING, logger="orchard_mapping.io.bags"):
        seq = read_rgbd(tmp_path / "bag", max_pair_dt_s=0.01)
    assert seq.dropped == 1
    assert "dropped 1 of 3" in caplog.text
    assert [int(f.color[0, 0, 0]) for f in seq] == [1, 3]
    np.testing.assert_allclose(seq.stamps, [1.0, 1.2])


def test_out_of_order_colour_stamps_warn_and_come_out_sorted(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    header_stamps = [1.0, 1.2, 1.1, 1.3]  # log times are increasing, header stamps are not
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        for k, t in enumerate(header_stamps):
            pixels = np.full((H, W, 3), k, np.uint8)
            bag.write_message(T.color, 2.0 + k, image_msg(t, W, H, "rgb8", 3 * W, pixels), IMAGE)
            bag.write_depth(T.depth, t, np.full((H, W), 1.0 + k))
    with caplog.at_level(logging.WARNING, logger="orchard_mapping.io.bags"):
        seq = read_rgbd(tmp_path / "bag")
    assert "out of order" in caplog.text
    np.testing.assert_allclose(seq.stamps, sorted(header_stamps))
    frames = list(seq)
    assert [int(f.color[0, 0, 0]) for f in frames] == [0, 2, 1, 3]
    assert [float(f.depth[0, 0]) for f in frames if f.depth is not None] == [1.0, 3.0, 2.0, 4.0]  # mm / 1000 exact
    assert [f.stamp for f in frames] == pytest.approx(sorted(header_stamps))


def test_padded_rows_are_cropped(tmp_path: Path) -> None:
    rgb = rgb_image(np.random.default_rng(2))
    padded = np.zeros((H, 3 * W + 8), np.uint8)
    padded[:, : 3 * W] = rgb.reshape(H, -1)
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_message(T.color, 1.0, image_msg(1.0, W, H, "rgb8", 3 * W + 8, padded), IMAGE)
    (frame,) = list(read_rgbd(tmp_path / "bag", mode="rgb"))
    np.testing.assert_array_equal(frame.color, rgb)


def test_iteration_is_repeatable_and_can_stop_early(tmp_path: Path) -> None:
    write_rgbd(tmp_path / "bag", n=5)
    seq = read_rgbd(tmp_path / "bag")
    first = next(iter(seq))
    again = list(seq)
    np.testing.assert_array_equal(first.color, again[0].color)
    assert len(again) == 5


# --------------------------------------------------------------------------- our messages


def _our_messages() -> dict[str, Any]:
    t = typestore().types
    hdr = msg_header(12.5, "odom_front")
    point = t["geometry_msgs/msg/Point"]
    vec = t["geometry_msgs/msg/Vector3"]
    cyl = t["orchard_mapping_msgs/msg/TrunkCylinder"](
        header=hdr,
        tree_id=7,
        side="front",
        base=point(x=1.0, y=-2.0, z=0.05),
        axis=vec(x=0.0, y=0.1, z=0.995),
        radius=0.061,
        length=0.9,
        radius_stddev=float("nan"),
        fit_rmse=0.004,
        inlier_count=812,
        flags=[],
    )
    cyl2 = dataclasses.replace(cyl, tree_id=-1, side="back", radius=0.07, radius_stddev=0.002,
                               flags=["detector_unavailable_nearby"])
    ground = t["orchard_mapping_msgs/msg/LocalGround"](
        header=hdr,
        tree_id=7,
        side="merged",
        point=point(x=1.0, y=-2.0, z=0.0),
        normal=vec(x=0.0, y=0.0, z=1.0),
        offset=-0.01,
        fit_rmse=0.02,
        inlier_count=4000,
        # what a ground fitter's answer adds (arrays: numpy, as rosbags reads them)
        kind="local",
        candidate_count=5200,
        support_area=0.42,
        support_offset=float("nan"),
        ground_cells=np.array([1.0, -2.0, 0.0, 1.04, -2.0, 0.001], np.float64),
        axis_point=point(x=1.0, y=-2.0, z=0.3),
        axis=vec(x=0.0, y=0.0, z=1.0),
        axis_radius=0.061,
        trunk_bottom=0.02,
        trunk_top=0.9,
        view_indices=np.array([0, 3], np.uint32),
        detection_indices=np.array([1, 0], np.uint32),
        point_indices=np.array([5, 17, 4000000000], np.uint32),
    )
    traits = t["orchard_mapping_msgs/msg/TreeTraits"](
        header=msg_header(12.5, "map"),
        tree_id=7,
        position=point(x=1.0, y=-2.0, z=0.0),
        trunk_diameter=0.122,
        height=2.75,
        canopy_volume=1.9,
        fruit_count=41,
        fruit_count_front=30,
        fruit_count_back=-1,
        flags=["one_side_missing", "trunk_occluded"],
        trunk_id_front=3,
        trunk_id_back=-1,
        trunk_diameter_front=0.121,
        trunk_diameter_back=float("nan"),
    )
    quat = t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.7071067811865476, w=0.7071067811865476)
    merge = t["orchard_mapping_msgs/msg/SideMerge"](
        header=msg_header(12.5, "odom_front"),
        child_frame_id="odom_back",
        scale=1.0,
        transform=t["geometry_msgs/msg/Transform"](translation=vec(x=0.5, y=3.0, z=0.0), rotation=quat),
        boundary_rmse=0.03,
        trunk_rmse=0.01,
        ground_rmse=0.02,
        matched_trunks=9,
        overlap=0.8,
    )
    return {
        "TrunkCylinder": cyl,
        "TrunkCylinderArray": t["orchard_mapping_msgs/msg/TrunkCylinderArray"](header=hdr, cylinders=[cyl, cyl2]),
        "LocalGround": ground,
        "LocalGroundArray": t["orchard_mapping_msgs/msg/LocalGroundArray"](header=hdr, grounds=[ground, ground]),
        "TreeTraits": traits,
        "TreeTraitsArray": t["orchard_mapping_msgs/msg/TreeTraitsArray"](header=hdr, trees=[traits]),
        "SideMerge": merge,
        "TrunkDetectionArray": t["orchard_mapping_msgs/msg/TrunkDetectionArray"](
            header=hdr, image_width=64, image_height=48, detections=[t["orchard_mapping_msgs/msg/TrunkDetection"](
                class_id=1, score=0.5, box=np.array([1.0, 2.0, 30.0, 40.0], np.float32), mask_x=1, mask_y=2,
                mask_width=2, mask_height=2, mask=np.array([1, 0, 1, 1], np.uint8))]),
        "SideMap": t["orchard_mapping_msgs/msg/SideMap"](
            header=msg_header(12.5, "odom_front"), side="front", encoding="orchard_mapping.side_map/1+npz",
            keyframes=40, trunks=2, cloud_points=1000, data=np.frombuffer(b"PK\x03\x04 payload", np.uint8)),
    }


@pytest.mark.parametrize("name", sorted(_our_messages()))
def test_our_message_round_trip(tmp_path: Path, name: str) -> None:
    msg = _our_messages()[name]
    msgtype = f"orchard_mapping_msgs/msg/{name}"
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_message(f"/orchard/{name.lower()}", 12.5, msg, msgtype)
        bag.write_message(f"/orchard/{name.lower()}", 13.0, msg, msgtype)
    got = list(iter_messages(tmp_path / "bag", f"/orchard/{name.lower()}"))
    assert [s for s, _ in got] == [12.5, 13.0]
    for _, back in got:
        assert type(back).__msgtype__ == msgtype
        assert same(back, msg)
    assert not same(got[0][1], dataclasses.replace(msg, header=msg_header(1.0)))  # the comparison can fail


def test_all_messages_in_one_bag_are_summarised(tmp_path: Path) -> None:
    msgs = _our_messages()
    with BagWriter(tmp_path / "bag") as bag:
        for name, msg in msgs.items():
            bag.write_message(f"/o/{name}", 1.0, msg, f"orchard_mapping_msgs/msg/{name}")
        bag.write_string(T.side, 3.0, "front")
    summary = describe_bag(tmp_path / "bag")
    assert summary.storage_id == "mcap"
    assert summary.start_s == 1.0 and summary.end_s == 3.0 and summary.duration_s == 2.0
    assert summary.size_bytes == sum(p.stat().st_size for p in (tmp_path / "bag").iterdir())
    assert summary.topics == tuple(
        sorted([(f"/o/{n}", f"orchard_mapping_msgs/msg/{n}", 1) for n in msgs] + [(T.side, "std_msgs/msg/String", 1)])
    )


# --------------------------------------------------------------------------- bare MCAP, MCAP cross-check


def test_bare_mcap_file_reads_like_the_folder(tmp_path: Path) -> None:
    _, colors, depths = write_rgbd(tmp_path / "bag", n=3)
    (mcap,) = (tmp_path / "bag").glob("*.mcap")
    bare = tmp_path / "elsewhere" / "recording.mcap"
    bare.parent.mkdir()
    shutil.copy(mcap, bare)
    seq = read_rgbd(bare)
    assert seq.bag == str(bare)
    assert seq.intrinsics == INTR
    frames = list(seq)
    assert len(frames) == 3
    for frame, rgb, depth in zip(frames, colors, depths, strict=True):
        np.testing.assert_array_equal(frame.color, rgb)
        assert frame.depth is not None and np.abs(frame.depth - depth).max() <= 0.0005 + 1e-6
    folder, file = describe_bag(tmp_path / "bag"), describe_bag(bare)
    assert file.storage_id == "mcap" and file.topics == folder.topics
    assert file.size_bytes == bare.stat().st_size
    assert (file.start_s, file.end_s) == (folder.start_s, folder.end_s) == (0.0, pytest.approx(1.202))


def test_mcap_library_decodes_our_file(tmp_path: Path) -> None:
    """Independent check: the `mcap` package reads the file; the embedded ros2msg schema alone decodes it."""
    from mcap.reader import make_reader
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    msgs = _our_messages()
    write_rgbd(tmp_path / "bag", n=2)
    bag_path = tmp_path / "bag2"
    rgb = rgb_image(np.random.default_rng(5))
    with BagWriter(bag_path) as bag:
        bag.write_message("/cyl", 4.25, msgs["TrunkCylinderArray"], "orchard_mapping_msgs/msg/TrunkCylinderArray")
        bag.write_color(T.color, 5.5, rgb)
    (mcap,) = bag_path.glob("*.mcap")
    with mcap.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 2
        decoded = {}
        for schema, channel, message in reader.iter_messages():
            assert schema is not None and schema.encoding == "ros2msg" and channel.message_encoding == "cdr"
            store = get_typestore(Stores.EMPTY)  # nothing but the schema stored in the file
            store.register(get_types_from_msg(schema.data.decode(), schema.name))
            decoded[channel.topic] = (message.log_time, store.deserialize_cdr(message.data, schema.name))
    log_ns, cyl = decoded["/cyl"]
    assert log_ns == 4_250_000_000
    assert same(cyl, msgs["TrunkCylinderArray"])
    log_ns, img = decoded[T.color]
    assert log_ns == 5_500_000_000 and (img.header.stamp.sec, img.header.stamp.nanosec) == (5, 500_000_000)
    np.testing.assert_array_equal(np.asarray(img.data).reshape(H, W, 3), rgb)


def test_compressed_bag_reads_back_the_same_and_is_smaller(tmp_path: Path) -> None:
    """compress=True: zstd chunks inside the MCAP file; read_rgbd and the `mcap` package read it as before."""
    from mcap.reader import make_reader

    smooth = np.tile(np.arange(W, dtype=np.uint8)[None, :, None], (H, 1, 3))  # compressible, like real images
    depth = np.full((H, W), 1.5)
    for name, compress in (("plain", False), ("zstd", True)):
        with BagWriter(tmp_path / name, compress=compress) as bag:
            bag.write_camera_info(T.camera_info, 0.0, INTR)
            for i in range(5):
                bag.write_color(T.color, 1.0 + 0.1 * i, smooth)
                bag.write_depth(T.depth, 1.0 + 0.1 * i, depth)
    sizes = {name: next((tmp_path / name).glob("*.mcap")).stat().st_size for name in ("plain", "zstd")}
    assert sizes["zstd"] < 0.5 * sizes["plain"], sizes
    frames = list(read_rgbd(tmp_path / "zstd"))
    assert len(frames) == 5
    for f in frames:
        np.testing.assert_array_equal(f.color, smooth)
        np.testing.assert_allclose(f.depth, 1.5, atol=5e-4)
    with next((tmp_path / "zstd").glob("*.mcap")).open("rb") as fh:
        reader = make_reader(fh)
        assert sum(1 for _ in reader.iter_messages()) == 11
        assert {c.compression for c in reader.get_summary().chunk_indexes} == {"zstd"}


# --------------------------------------------------------------------------- atomic writer


def test_exception_inside_with_leaves_nothing(tmp_path: Path) -> None:
    with pytest.raises(RuntimeError, match="boom"), BagWriter(tmp_path / "bag") as bag:
        bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.uint8))
        raise RuntimeError("boom")
    assert not (tmp_path / "bag").exists()
    assert list(tmp_path.iterdir()) == []  # no partial sibling folder either


def test_bag_appears_only_on_close(tmp_path: Path) -> None:
    bag = BagWriter(tmp_path / "bag")
    with bag:
        bag.write_string(T.side, 1.0, "front")
        assert not (tmp_path / "bag").exists()
    assert sorted(p.name for p in (tmp_path / "bag").iterdir()) == ["bag.mcap", "metadata.yaml"]
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]


def test_existing_output_needs_overwrite(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_string(T.side, 1.0, "front")
    with pytest.raises(BagError, match="overwrite=True"), BagWriter(tmp_path / "bag"):
        pass
    with BagWriter(tmp_path / "bag", overwrite=True) as bag:
        bag.write_string(T.side, 2.0, "back")
    assert [m.data for _, m in iter_messages(tmp_path / "bag", T.side)] == ["back"]
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]
    # a failed overwrite keeps the old bag
    with pytest.raises(RuntimeError), BagWriter(tmp_path / "bag", overwrite=True) as bag:
        bag.write_string(T.side, 3.0, "front")
        raise RuntimeError
    assert [m.data for _, m in iter_messages(tmp_path / "bag", T.side)] == ["back"]


def test_writer_rejects_misuse(tmp_path: Path) -> None:
    bag = BagWriter(tmp_path / "bag")
    with pytest.raises(BagError, match="not open"):
        bag.write_string(T.side, 1.0, "front")
    with bag:
        bag.write_string(T.side, 1.0, "front")
        with pytest.raises(BagError, match="cannot also write"):
            bag.write_message(T.side, 1.0, msg_header(1.0), "std_msgs/msg/Header")
        with pytest.raises(BagError, match="unknown message type"):
            bag.write_message("/x", 1.0, None, "nope_msgs/msg/Nope")
        with pytest.raises(ValueError, match="uint8"):
            bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.float32))
        with pytest.raises(ValueError, match="encoding"):
            bag.write_depth(T.depth, 1.0, np.zeros((H, W)), "8UC1")  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="stamp"):
            bag.write_string(T.side, -1.0, "front")


# --------------------------------------------------------------------------- errors


def test_missing_colour_topic(tmp_path: Path) -> None:
    write_rgbd(tmp_path / "bag", n=1)
    topics = TopicsConfig(color="/other/image")
    with pytest.raises(MissingTopicError) as info:
        read_rgbd(tmp_path / "bag", topics)
    text = str(info.value)
    assert "/other/image" in text and str(tmp_path / "bag") in text and T.depth in text  # names what is there
    assert info.value.topic == "/other/image" and info.value.bag == str(tmp_path / "bag")


def test_missing_depth_topic_only_matters_in_rgbd_mode(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.uint8))
    with pytest.raises(MissingTopicError, match="depth topic not in bag") as info:
        read_rgbd(tmp_path / "bag")
    assert info.value.topic == T.depth and T.color in str(info.value)
    assert len(read_rgbd(tmp_path / "bag", mode="rgb")) == 1


@pytest.mark.parametrize(("topic", "encoding", "bpp"), [(T.color, "yuv422", 2), (T.depth, "8UC1", 1)])
def test_unknown_encoding(tmp_path: Path, topic: str, encoding: str, bpp: int) -> None:
    write_rgbd(tmp_path / "bag", n=1)
    with BagWriter(tmp_path / "bad") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.uint8))
        bag.write_depth(T.depth, 1.0, np.ones((H, W)))
        bag.write_message(topic, 1.1, image_msg(1.1, W, H, encoding, bpp * W, np.zeros(bpp * W * H)), IMAGE)
    with pytest.raises(BagFormatError) as info:
        read_rgbd(tmp_path / "bad")
    text = str(info.value)
    assert "'encoding'" in text and repr(encoding) in text and topic in text and str(tmp_path / "bad") in text


def test_colour_depth_size_mismatch(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.uint8))
        bag.write_depth(T.depth, 1.0, np.ones((24, 32)))
    with pytest.raises(BagFormatError) as info:
        read_rgbd(tmp_path / "bag")
    text = str(info.value)
    assert "32x24" in text and "64x48" in text and T.depth in text


def test_data_length_not_height_times_step(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        bag.write_message(T.color, 1.0, image_msg(1.0, W, H, "rgb8", 3 * W, np.zeros(3 * W * H - 5)), IMAGE)
    with pytest.raises(BagFormatError) as info:
        read_rgbd(tmp_path / "bag", mode="rgb")
    text = str(info.value)
    assert "'data'" in text and f"{3 * W * H - 5} bytes" in text and "height*step" in text and T.color in text


def test_missing_camera_info(tmp_path: Path) -> None:
    write_rgbd(tmp_path / "bag", n=1, camera_info=False)
    with pytest.raises(CalibrationError) as info:
        read_rgbd(tmp_path / "bag")
    assert "'k'" in str(info.value) and info.value.topic == T.camera_info and info.value.bag == str(tmp_path / "bag")


@pytest.mark.parametrize("bad", [{"fx": 0.0}, {"fy": float("nan")}, {"fx": -5.0}])
def test_invalid_focal_length(tmp_path: Path, bad: dict[str, float]) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, dataclasses.replace(INTR, **bad))
        bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.uint8))
    with pytest.raises(CalibrationError) as info:
        read_rgbd(tmp_path / "bag", mode="rgb")
    assert "field 'k'" in str(info.value) and T.camera_info in str(info.value)


def test_camera_info_size_differs_from_images(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, dataclasses.replace(INTR, width=640, height=480))
        bag.write_color(T.color, 1.0, np.zeros((H, W, 3), np.uint8))
    with pytest.raises(CalibrationError, match="640x480"):
        read_rgbd(tmp_path / "bag", mode="rgb")


def test_nonexistent_path(tmp_path: Path) -> None:
    with pytest.raises(BagReadError, match="no such file or folder") as info:
        read_rgbd(tmp_path / "nope")
    assert str(tmp_path / "nope") in str(info.value)
    assert isinstance(info.value.__cause__, FileNotFoundError)


def test_truncated_mcap(tmp_path: Path) -> None:
    # cut half way through its one chunk: the whole messages at the chunk's front are read (io.salvage), the
    # first frame here; a cut before any whole message is refused (test_bad_input.py)
    stamps, colors, _ = write_rgbd(tmp_path / "bag", n=3)
    (mcap,) = (tmp_path / "bag").glob("*.mcap")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap.read_bytes()[: mcap.stat().st_size // 2])
    seq = read_rgbd(cut)
    assert seq.notes.cut_short is not None and list(seq.stamps) == stamps[:1]
    np.testing.assert_array_equal(next(iter(seq)).color, colors[0])


@pytest.mark.parametrize("kind", ["empty_folder", "text_file", "garbage_mcap", "bad_metadata"])
def test_not_a_bag(tmp_path: Path, kind: str) -> None:
    if kind == "empty_folder":
        path = tmp_path / "folder"
        path.mkdir()
    elif kind == "text_file":
        path = tmp_path / "notes.txt"
        path.write_text("hello")
    elif kind == "garbage_mcap":
        path = tmp_path / "x.mcap"
        path.write_bytes(b"\x89MCAP0\r\n" + b"\x00" * 40)
    else:
        path = tmp_path / "bag"
        path.mkdir()
        (path / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: 9}\n")
    with pytest.raises(BagReadError) as info:
        read_rgbd(path)
    assert info.value.__cause__ is not None  # rosbags' exception is kept
    assert str(path) in str(info.value)
    with pytest.raises(BagReadError):
        describe_bag(path)


def test_empty_bag(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag"):
        pass
    with pytest.raises(EmptyBagError, match="no messages"):
        read_rgbd(tmp_path / "bag")
    summary = describe_bag(tmp_path / "bag")
    assert summary.topics == () and summary.duration_s == 0.0 and summary.start_s is None


def test_colour_topic_without_messages(tmp_path: Path) -> None:
    # A connection with no messages: BagWriter never makes one, so use rosbags directly.
    store = typestore()
    writer = Writer(tmp_path / "bag", version=9, storage_plugin=StoragePlugin.MCAP)
    with writer:
        writer.add_connection(T.color, IMAGE, typestore=store)
        side = writer.add_connection(T.side, "std_msgs/msg/String", typestore=store)
        writer.write(
            side, 1, store.serialize_cdr(store.types["std_msgs/msg/String"](data="front"), "std_msgs/msg/String")
        )
    with pytest.raises(EmptyBagError) as err:
        read_rgbd(tmp_path / "bag", mode="rgb")
    assert "colour topic" in str(err.value) and err.value.topic == T.color
    assert describe_bag(tmp_path / "bag").topics == ((T.color, IMAGE, 0), (T.side, "std_msgs/msg/String", 1))


def test_no_pairs_at_all(tmp_path: Path) -> None:
    write_rgbd(tmp_path / "bag", n=2, depth_offset=0.05)
    with pytest.raises(EmptyBagError, match=r"within 0\.01 s"):
        read_rgbd(tmp_path / "bag", max_pair_dt_s=0.01)
    assert len(read_rgbd(tmp_path / "bag", max_pair_dt_s=0.06)) == 2


def test_all_zero_depth_is_raised_before_any_frame(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_camera_info(T.camera_info, 0.0, INTR)
        for t in (1.0, 1.1):
            bag.write_color(T.color, t, np.zeros((H, W, 3), np.uint8))
            bag.write_depth(T.depth, t, np.zeros((H, W)))
    with pytest.raises(BagFormatError) as info:
        read_rgbd(tmp_path / "bag")
    text = str(info.value)
    assert "no valid depth" in text and "mode='rgb'" in text and T.depth in text
    assert len(read_rgbd(tmp_path / "bag", mode="rgb")) == 2


def test_wrong_message_type_on_colour_topic(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_string(T.color, 1.0, "not an image")
    with pytest.raises(BagFormatError, match="sensor_msgs/msg/Image"):
        read_rgbd(tmp_path / "bag")


def test_iter_messages_missing_topic(tmp_path: Path) -> None:
    with BagWriter(tmp_path / "bag") as bag:
        bag.write_string(T.side, 1.0, "front")
    with pytest.raises(MissingTopicError, match=T.side):
        list(iter_messages(tmp_path / "bag", "/nope"))
