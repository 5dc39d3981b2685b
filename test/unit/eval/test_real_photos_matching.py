"""The real-photo benchmark's matching (benchmarks/real_photos.py) on tiny synthetic frames, not on the photos."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK, Detection

_PATH = Path(__file__).resolve().parents[3] / "benchmarks" / "real_photos.py"


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("real_photos_bench", _PATH)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    try:
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.modules.pop(spec.name, None)


def _cols(x0: int, x1: int, h: int = 40, w: int = 100) -> np.ndarray:
    """A trunk-like mask: full-height columns x0..x1-1."""
    m = np.zeros((h, w), bool)
    m[:, x0:x1] = True
    return m


def test_mask_iou_0_6_counts_and_0_4_does_not(bench):
    gt = [_cols(10, 20)]  # 10 columns
    hit = Detection.from_mask(_cols(10, 16), CLASS_TRUNK, 0.9)  # IoU 6/10 = 0.6
    miss = Detection.from_mask(_cols(10, 14), CLASS_TRUNK, 0.9)  # IoU 4/10 = 0.4
    m = bench.match_frame(gt, [hit])
    assert (m.true_trunks, m.found_trunk, m.found_any, m.false_trunks) == (1, 1, 1, 0)
    m = bench.match_frame(gt, [miss])
    assert (m.found_trunk, m.found_any, m.false_trunks) == (0, 0, 1)


def test_post_label_counts_only_for_trunk_or_post(bench):
    gt = [_cols(10, 20)]
    post = Detection.from_mask(_cols(10, 20), CLASS_POST, 0.9)
    m = bench.match_frame(gt, [post])
    assert (m.found_trunk, m.found_any, m.false_trunks) == (0, 1, 0)


def test_one_detection_per_trunk_and_duplicates_are_false(bench):
    gt = [_cols(10, 20), _cols(60, 70)]
    dets = [Detection.from_mask(_cols(10, 20), CLASS_TRUNK, 0.9),
            Detection.from_mask(_cols(11, 20), CLASS_TRUNK, 0.8),  # second detection of the first trunk
            Detection.from_mask(_cols(60, 69), CLASS_TRUNK, 0.7)]
    m = bench.match_frame(gt, dets)
    assert (m.true_trunks, m.found_trunk, m.false_trunks) == (2, 2, 1)


def test_boxes_match_by_box_iou(bench):
    gt = [np.array([10.0, 0.0, 20.0, 40.0])]
    det = Detection(CLASS_TRUNK, 0.9, np.array([10.0, 0.0, 17.0, 40.0]), _cols(10, 17))  # box IoU 0.7
    assert bench.match_frame(gt, [det], kind="box").found_trunk == 1
    det = Detection(CLASS_TRUNK, 0.9, np.array([10.0, 0.0, 14.0, 40.0]), _cols(10, 14))  # box IoU 0.4
    assert bench.match_frame(gt, [det], kind="box").found_trunk == 0


def test_caliper_centre_rule_and_diameter(bench):
    w, h = 100, 40
    centre = Detection.from_mask(_cols(46, 54, h, w), CLASS_TRUNK, 0.6)
    side = Detection.from_mask(_cols(5, 13, h, w), CLASS_TRUNK, 0.9)  # a neighbouring tree
    assert bench.centre_detection([side, centre], w, h, (CLASS_TRUNK,)) is centre
    assert bench.centre_detection([side], w, h, (CLASS_TRUNK,)) is None
    # 8 px wide at 1.5 m with fx 200 px: 60 mm
    depth = np.full((h, w), 1.5, np.float32)
    assert bench.mask_diameter_mm(centre.mask, depth, 200.0) == pytest.approx(60.0)
