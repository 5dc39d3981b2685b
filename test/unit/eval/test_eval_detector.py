"""The detector's scores (eval.detector, `orchard-map eval-detector`): COCO mask AP from pycocotools.

A model with fixed outputs (docs/detector.md's contract) is scored on one annotated frame whose truth
it matches exactly except where an error is planted: a trunk it misses, a trunk it calls a post. The
planted errors come back in the per-class, per-size and class-blind figures.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

pytest.importorskip("onnx")

from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK  # noqa: E402
from orchard_mapping.eval.detector import evaluate_detector  # noqa: E402
from orchard_mapping.io.coco import mask_rle  # noqa: E402

H, W = 48, 64  # model input; the frame is 4x larger (detections are scaled back by the runtime)
SCALE = 4
TRUNK = (slice(10, 40), slice(20, 30))  # model input px: 30 x 10 -> 4800 px in the frame (COCO medium)
POST = (slice(2, 47), slice(50, 64))  # 45 x 14 -> 10080 px (large)
HIDDEN_TRUNK = (slice(0, 20), slice(0, 20))  # frame px: 400 px (small), never detected


def _frame_mask(region: tuple[slice, slice], scale: int = SCALE) -> np.ndarray:
    m = np.zeros((H * SCALE, W * SCALE), bool)
    m[region[0].start * scale:region[0].stop * scale, region[1].start * scale:region[1].stop * scale] = True
    return m


def _coco_folder(tmp_path, hidden_crowd: int = 0, trunk_specks: np.ndarray | None = None) -> str:
    img = np.full((H * SCALE, W * SCALE, 3), 90, np.uint8)
    cv2.imwrite(str(tmp_path / "frame.png"), img)
    trunk = _frame_mask(TRUNK) if trunk_specks is None else _frame_mask(TRUNK) | trunk_specks
    truth = [(CLASS_TRUNK, trunk), (CLASS_POST, _frame_mask(POST)),
             (CLASS_TRUNK, _frame_mask(HIDDEN_TRUNK, scale=1))]
    anns = []
    for k, (c, m) in enumerate(truth):
        rle = mask_rle(m)
        crowd = hidden_crowd if k == 2 else 0
        anns.append({"id": k + 1, "image_id": 1, "category_id": c, "iscrowd": crowd, "area": int(m.sum()),
                     "segmentation": {"size": rle["size"], "counts": rle["counts"].decode("ascii")}})
    doc = {"images": [{"id": 1, "file_name": "frame.png", "width": W * SCALE, "height": H * SCALE}],
           "annotations": anns, "categories": [{"id": CLASS_TRUNK, "name": "trunk"}, {"id": CLASS_POST, "name": "post"}]}
    (tmp_path / "instances.json").write_text(json.dumps(doc))
    return tmp_path


def _detector(write, path, trunk_label: int):
    masks = np.zeros((2, 1, H, W), np.float32)
    masks[0, 0][TRUNK] = 0.9
    masks[1, 0][POST] = 0.9
    values = {"boxes": np.array([[20, 10, 30, 40], [50, 2, 64, 47]], np.float32),
              "labels": np.array([trunk_label, CLASS_POST], np.int64),
              "scores": np.array([0.9, 0.8], np.float32), "masks": masks}
    return write(path, values, input_shape=[3, H, W])


def test_a_missed_sliver_shows_in_the_trunk_and_small_scores(tmp_path, constant_detector):
    data = _coco_folder(tmp_path)
    s = evaluate_detector(_detector(constant_detector, tmp_path / "m.onnx", CLASS_TRUNK), [data])
    assert (s.images, s.instances) == (1, 3)
    assert s.ap_post == pytest.approx(1.0) and s.ap50_post == pytest.approx(1.0)
    # one of two trunks found, exactly: precision 1 up to recall 0.5 (51 of COCO's 101 recall points)
    assert s.ap_trunk == pytest.approx(51 / 101) and s.ap50_trunk == pytest.approx(51 / 101)
    assert s.ap_small == pytest.approx(0.0)  # the hidden trunk's sliver
    assert s.ap_medium == pytest.approx(1.0) and s.ap_large == pytest.approx(1.0)
    assert s.ap50_any_class == pytest.approx(67 / 101)  # 2 of 3 instances, either class


def test_a_trunk_called_a_post_costs_the_trunk_not_the_class_blind_score(tmp_path, constant_detector):
    data = _coco_folder(tmp_path)
    right = evaluate_detector(_detector(constant_detector, tmp_path / "a.onnx", CLASS_TRUNK), [data])
    confused = evaluate_detector(_detector(constant_detector, tmp_path / "b.onnx", CLASS_POST), [data])
    assert confused.ap_trunk == pytest.approx(0.0) and confused.ap50_trunk == pytest.approx(0.0)
    assert confused.ap50_post < right.ap50_post  # the trunk is a false post
    assert confused.ap50 < right.ap50 - 0.2
    assert confused.ap50_any_class == pytest.approx(right.ap50_any_class)


def test_a_region_to_ignore_is_neither_missed_nor_scored_unless_asked(tmp_path, constant_detector):
    data = _coco_folder(tmp_path, hidden_crowd=1)  # the hidden trunk's sliver marked iscrowd (COCO: ignore)
    model = _detector(constant_detector, tmp_path / "m.onnx", CLASS_TRUNK)
    s = evaluate_detector(model, [data])
    assert (s.instances, s.ignored) == (2, 1)
    assert s.ap_trunk == pytest.approx(1.0) and s.ap50 == pytest.approx(1.0)
    counted = evaluate_detector(model, [data], ignore_crowd=False)  # as if every visible pixel had to be found
    assert (counted.instances, counted.ignored) == (3, 0)
    assert counted.ap_trunk == pytest.approx(51 / 101)


def test_specks_seen_through_leaves_are_scored_only_without_solid_outlines(tmp_path, constant_detector):
    """The trunk's annotation also holds specks of it seen through the canopy above its bark (2 x 2 px, 4 px
    apart, 8 px and more above it); the model outlines the bark. Scored on whole instances the specks cut
    its IoU (under 0.8: it fails AP's higher thresholds); scored on solid outlines it is exact."""
    specks = np.zeros((H * SCALE, W * SCALE), bool)
    for v in range(0, TRUNK[0].start * SCALE - 8, 4):
        for u in range(40, 160, 4):
            specks[v:v + 2, u:u + 2] = True
    data = _coco_folder(tmp_path, hidden_crowd=1, trunk_specks=specks)
    model = _detector(constant_detector, tmp_path / "m.onnx", CLASS_TRUNK)
    whole = evaluate_detector(model, [data])
    outlined = evaluate_detector(model, [data], solid_outlines=True)
    assert whole.ap50_trunk == pytest.approx(1.0) and whole.ap_trunk < 0.75
    assert outlined.ap_trunk == pytest.approx(1.0) and outlined.solid_outlines
    assert outlined.ap_post == pytest.approx(whole.ap_post) == pytest.approx(1.0)  # a post has no specks


def _evaluated(found_in: list[bool]):
    """COCOeval (segm, as evaluate_detector runs it) of frames that each hold one trunk and one post; the post is
    always found exactly, the trunk exactly in the frames where found_in says so and not at all elsewhere."""
    from pycocotools.coco import COCO

    from orchard_mapping.eval.detector import coco_eval

    trunk, post = _frame_mask(TRUNK), _frame_mask(POST)
    images, anns, results = [], [], []
    for i, found in enumerate(found_in, start=1):
        images.append({"id": i, "width": W * SCALE, "height": H * SCALE})
        for c, m in ((CLASS_TRUNK, trunk), (CLASS_POST, post)):
            rle = mask_rle(m)
            anns.append({"id": len(anns) + 1, "image_id": i, "category_id": c, "segmentation": rle,
                         "area": float(m.sum()), "bbox": [0, 0, 1, 1], "iscrowd": 0})
            if found or c == CLASS_POST:
                results.append({"image_id": i, "category_id": c, "segmentation": rle, "score": 0.9})
    gt = COCO()
    gt.dataset = {"images": images, "annotations": anns,
                  "categories": [{"id": CLASS_TRUNK, "name": "trunk"}, {"id": CLASS_POST, "name": "post"}]}
    gt.createIndex()
    return coco_eval(gt, gt.loadRes(results), use_categories=True)


def test_frames_are_resampled_by_the_recording_their_name_gives():
    from pathlib import Path

    from orchard_mapping.eval.detector import recording_of

    assert recording_of(Path("images/scene0007_front_000013.jpg")) == str(Path("images/scene0007_front"))
    assert recording_of(Path("a/row-12.png")) == str(Path("a/row"))
    assert recording_of(Path("a/frame.png")) == str(Path("a/frame"))  # no number: a recording of its own


def test_one_recording_resampled_gives_back_its_own_scores():
    """Every draw of a single recording is that recording whole: the interval closes on COCO's own figures,
    which checks that the per-image matches are re-accumulated in COCOeval's layout."""
    from orchard_mapping.eval.detector import bootstrap_intervals

    ev = _evaluated([True, False, True, True, False])
    iv = bootstrap_intervals(ev, ["row"] * 5, draws=20)
    assert iv["ap_interval"] == pytest.approx((ev.stats[0], ev.stats[0]))
    assert iv["ap50_interval"] == pytest.approx((ev.stats[1], ev.stats[1]))
    trunk50 = 61 / 101  # 3 of 5 trunks at precision 1: COCO's recall points 0, 0.01, ..., 0.60
    assert iv["ap50_trunk_interval"] == pytest.approx((trunk50, trunk50))


def test_the_interval_spans_what_resampling_the_recordings_can_give():
    """Recording a finds every trunk, recording b none: draws of (a, a) score the trunk 1, of (b, b) 0; with
    200 draws both appear (each has 1 chance in 4), so the 95 % interval of trunk AP50 is [0, 1] while the
    post's perfect score keeps AP50 at 0.5 or more."""
    from orchard_mapping.eval.detector import bootstrap_intervals

    ev = _evaluated([True, True, False, False])
    iv = bootstrap_intervals(ev, ["a", "a", "b", "b"], draws=200)
    assert iv["ap50_trunk_interval"] == pytest.approx((0.0, 1.0))
    assert iv["ap50_interval"] == pytest.approx((0.5, 1.0))
    with pytest.raises(ValueError, match="3 recording names for 4"):
        bootstrap_intervals(ev, ["a", "a", "b"], draws=5)
