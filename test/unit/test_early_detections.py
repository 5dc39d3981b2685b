"""Trunk detection beside the front end (pipeline.EarlyDetections): which keyframes reach the detector, in
what order, and what comes back to the side's finishing."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import numpy as np

from orchard_mapping.config import load_config
from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK, Detection
from orchard_mapping.core.types import CameraIntrinsics, ImagePatch, RGBDFrame
from orchard_mapping.pipeline import EarlyDetections

INTR = CameraIntrinsics(64, 48, 60.0, 60.0, 31.5, 23.5)


def _keyframe(frame_index: int, x: float) -> SimpleNamespace:
    T = np.eye(4)
    T[0, 3] = x
    return SimpleNamespace(frame_index=frame_index, T_odom_cam=T)


def _frame(i: int) -> RGBDFrame:
    color = np.full((48, 64, 3), i % 256, np.uint8)  # the frame's number in its pixels
    return RGBDFrame(stamp=0.1 * i, color=color, depth=np.ones((48, 64), np.float32), intrinsics=INTR, index=i)


def test_keyframes_detect_every_m_apart_reach_the_detector_in_order_and_come_back_whole():
    cfg = load_config(overrides={"trunks": {"detect_every_m": 0.15}})
    asked: list[tuple[int, float, str]] = []

    def detect(color: np.ndarray, stamp: float):
        asked.append((int(color[0, 0, 0]), stamp, threading.current_thread().name))
        if int(color[0, 0, 0]) == 12:
            return None  # the detector did not answer for this one
        mask = np.zeros((48, 64), bool)
        mask[10:40, 20 + int(color[0, 0, 0]) % 5:30] = True
        return [Detection.from_mask(mask, CLASS_TRUNK, 0.9), Detection.from_mask(mask[::-1], CLASS_POST, 0.8)]

    early = EarlyDetections(cfg, "front", detect)
    # keyframes 0.05 m apart along x: every third is 0.15 m on from the last one detected on
    xs = np.arange(20) * 0.05
    for i, x in enumerate(xs):
        early.offer(_keyframe(i, float(x)), _frame(i))
    early.offer(_keyframe(20, float("nan")), _frame(20))  # a keyframe without a pose is not detected on
    got = early.results()

    assert [a[0] for a in asked] == [0, 3, 6, 9, 12, 15, 18] == sorted(got)
    assert [a[1] for a in asked] == [0.1 * i for i in (0, 3, 6, 9, 12, 15, 18)]
    assert all(name.startswith("trunk-detector-front") for _, _, name in asked)  # not the front end's thread
    assert got[12] is None
    for i in (0, 3, 6, 9, 15, 18):
        trunk, post = got[i]
        assert isinstance(trunk.mask, ImagePatch) and trunk.mask.nbytes < 48 * 64  # kept as the part around it
        want = np.zeros((48, 64), bool)
        want[10:40, 20 + i % 5:30] = True
        assert np.array_equal(np.asarray(trunk.mask, bool), want)
        assert np.array_equal(np.asarray(post.mask, bool), want[::-1])
        assert (trunk.class_id, post.class_id) == (CLASS_TRUNK, CLASS_POST)


def _views(view_depth: str):
    from orchard_mapping.pipeline import TrunkViews

    cfg = load_config(overrides={"trunks": {"view_depth": view_depth}, "fusion": {"depth_max_m": 3.0},
                                 "semantic_ba": {"use_posts": False}})
    mask = np.zeros((48, 64), bool)
    mask[10:40, 28:34] = True
    found = {7: [Detection.from_mask(mask, CLASS_TRUNK, 0.9)], 8: [Detection.from_mask(mask, CLASS_POST, 0.9)]}
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    return TrunkViews(cfg, np.array([0.0, 0.1, 0.2]), poses, INTR, found, [6, 7, 8])


def test_trunk_views_keep_the_raw_depth_and_ask_for_no_cleaning_unless_told_to():
    depth = np.full((48, 64), 1.2, np.float32)
    depth[20, 30] = 4.0  # beyond fusion.depth_max_m: not fused, so not read either
    raw = _views("raw")
    assert raw.select(0, np.zeros((48, 64, 3), np.uint8), depth) is False  # no detection there
    assert raw.select(2, np.zeros((48, 64, 3), np.uint8), depth) is False  # posts only
    assert raw.select(1, np.zeros((48, 64, 3), np.uint8), depth) is False  # kept at once, nothing to clean
    (view,) = raw.views
    d = np.asarray(view.depth)
    assert view.keyframe == 1 and d[20, 30] == 0.0 and d[21, 30] == np.float32(1.2)

    cleaned = _views("cleaned")
    region = cleaned.select(1, np.zeros((48, 64, 3), np.uint8), depth)
    assert isinstance(region, tuple) and region[0] <= 10 and region[2] >= 40 and not cleaned.views
    depth_clean = np.where(depth < 2, depth, 0).astype(np.float32)
    cleaned(1, depth_clean, None)  # fusion hands the cleaned depth over
    assert [v.keyframe for v in cleaned.views] == [1]
    assert np.asarray(cleaned.views[0].depth)[21, 30] == np.float32(1.2)


def test_an_unknown_view_depth_is_a_config_error():
    import pytest

    from orchard_mapping.errors import ConfigError

    with pytest.raises(ConfigError, match="trunks.view_depth must be 'raw' or 'cleaned', got 'smoothed'"):
        load_config(overrides={"trunks": {"view_depth": "smoothed"}})
