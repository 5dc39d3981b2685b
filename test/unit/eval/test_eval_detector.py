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
