"""The ONNX detector runtime (core.detection): the model contract of docs/detector.md and its errors.

The models here are built with `onnx` and return fixed detections, so the runtime's pre- and
post-processing (resizing, thresholds, mapping back to the frame) is checked exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
from onnx import TensorProto  # noqa: E402

from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK, DetectorError, OnnxTrunkDetector  # noqa: E402

H, W = 48, 64  # model input


def _masks() -> np.ndarray:
    m = np.zeros((3, 1, H, W), np.float32)
    m[0, 0, 10:40, 20:30] = 0.9  # a trunk
    m[1, 0, 5:45, 50:56] = 0.8  # a post
    m[2, 0, 0:10, 0:10] = 0.9  # a weak detection (score below threshold)
    return m


def _model(write, path: Path, *, outputs: tuple[str, ...] = ("boxes", "labels", "scores", "masks"),
           input_shape: tuple[int, ...] | list[int] = (3, H, W), input_type: int = TensorProto.FLOAT, box_masks: bool = False,
           values: dict[str, np.ndarray] | None = None) -> Path:
    """write: the constant_detector fixture (test/conftest.py)."""
    values = values or {
        "boxes": np.array([[20, 10, 30, 40], [50, 5, 56, 45], [0, 0, 10, 10]], np.float32),
        "labels": np.array([CLASS_TRUNK, CLASS_POST, CLASS_TRUNK], np.int64),
        "scores": np.array([0.95, 0.7, 0.2], np.float32),
        # box-relative masks (Mask R-CNN's 28 x 28 per box) or masks pasted into the input image
        "masks": np.full((3, 1, 28, 28), 0.9, np.float32) if box_masks else _masks(),
    }
    return write(path, values, outputs=outputs, input_shape=list(input_shape), input_type=input_type)


def test_detections_are_thresholded_and_mapped_back_to_the_frame(tmp_path, constant_detector):
    det = OnnxTrunkDetector(_model(constant_detector, tmp_path / "m.onnx"), score_threshold=0.5, mask_threshold=0.5)
    frame = np.zeros((2 * H, 2 * W, 3), np.uint8)  # twice the model's input: results scaled by 2
    out = det.detect(frame)
    assert [d.class_id for d in out] == [CLASS_TRUNK, CLASS_POST]
    np.testing.assert_allclose(out[0].box, [40, 20, 60, 80])
    assert out[0].mask.shape == (2 * H, 2 * W)
    v, u = np.nonzero(out[0].mask)
    assert (v.min(), v.max(), u.min(), u.max()) == (20, 79, 40, 59)
    assert out[1].score == pytest.approx(0.7)
    assert len(OnnxTrunkDetector(tmp_path / "m.onnx", score_threshold=0.75).detect(frame)) == 1


def test_a_second_detection_of_part_of_a_trunk_is_dropped(tmp_path, constant_detector):
    """Box NMS lets through a half-trunk beside the whole one (box IoU 0.5); its mask lies inside the
    better-scored trunk's and is dropped. A post touching the trunk keeps its own mask."""
    m = np.zeros((3, 1, H, W), np.float32)
    m[0, 0, 10:40, 20:30] = 0.9  # the trunk
    m[1, 0, 10:40, 20:25] = 0.9  # its left half, detected again with a lower score
    m[2, 0, 10:40, 29:35] = 0.9  # a post overlapping the trunk's edge column
    values = {"boxes": np.array([[20, 10, 30, 40], [20, 10, 25, 40], [29, 10, 35, 40]], np.float32),
              "labels": np.array([CLASS_TRUNK, CLASS_TRUNK, CLASS_POST], np.int64),
              "scores": np.array([0.9, 0.7, 0.8], np.float32),
              "masks": m}
    frame = np.zeros((H, W, 3), np.uint8)
    out = OnnxTrunkDetector(_model(constant_detector, tmp_path / "m.onnx", values=values)).detect(frame)
    assert [(d.class_id, int(d.mask.sum())) for d in out] == [(CLASS_TRUNK, 300), (CLASS_POST, 180)]
    kept = OnnxTrunkDetector(tmp_path / "m.onnx", max_overlap=1.0).detect(frame)  # suppression off
    assert sorted(d.score for d in kept) == pytest.approx([0.7, 0.8, 0.9])


def test_the_test_time_flip_maps_the_mirrors_detections_back_and_drops_their_duplicates(tmp_path, constant_detector):
    """The constant model finds the same trunk (u 20-30) and post (u 50-56) in the frame and in its mirror. Mirrored
    back, the mirror's trunk stands at u 34-44 (a trunk of its own, box and mask mirrored) and its post at u 8-14;
    a trunk that is symmetric about the frame's centre (u 27-37) is found twice at one place: kept once, with
    the mirror's copy dropped as a duplicate."""
    frame = np.zeros((2 * H, 2 * W, 3), np.uint8)  # results scaled by 2
    model = _model(constant_detector, tmp_path / "m.onnx")
    plain = OnnxTrunkDetector(model).detect(frame)
    both = OnnxTrunkDetector(model, flip=True).detect(frame)
    assert [d.class_id for d in both] == [CLASS_TRUNK, CLASS_TRUNK, CLASS_POST, CLASS_POST]
    assert [d.score for d in both] == pytest.approx([0.95, 0.95, 0.7, 0.7])
    assert np.array_equal(both[0].mask, plain[0].mask) and np.array_equal(both[2].mask, plain[1].mask)
    np.testing.assert_allclose(both[1].box, [2 * W - 60, 20, 2 * W - 40, 80])  # x 68-88
    v, u = np.nonzero(both[1].mask)
    assert (v.min(), v.max(), u.min(), u.max()) == (20, 79, 68, 87)
    assert np.array_equal(both[3].mask, plain[1].mask[:, ::-1])
    m = np.zeros((1, 1, H, W), np.float32)
    m[0, 0, 10:40, 27:37] = 0.9
    centred = {"boxes": np.array([[27, 10, 37, 40]], np.float32), "labels": np.array([CLASS_TRUNK], np.int64),
               "scores": np.array([0.9], np.float32), "masks": m}
    one = OnnxTrunkDetector(_model(constant_detector, tmp_path / "c.onnx", values=centred), flip=True).detect(frame)
    assert len(one) == 1 and int(one[0].mask.sum()) == 4 * 300


def test_box_relative_masks_are_pasted_into_their_boxes(tmp_path, constant_detector):
    det = OnnxTrunkDetector(_model(constant_detector, tmp_path / "m.onnx", box_masks=True))
    out = det.detect(np.zeros((2 * H, 2 * W, 3), np.uint8))
    assert [d.class_id for d in out] == [CLASS_TRUNK, CLASS_POST]
    v, u = np.nonzero(out[0].mask)
    assert (v.min(), v.max(), u.min(), u.max()) == (20, 79, 40, 59)  # the box (x 40-60, y 20-80) filled
    assert out[0].mask.sum() == 20 * 60


def test_a_missing_or_broken_model_is_one_typed_error_naming_the_file(tmp_path, constant_detector):
    with pytest.raises(DetectorError, match=r"nope\.onnx: no such file"):
        OnnxTrunkDetector(tmp_path / "nope.onnx")
    bad = tmp_path / "text.onnx"
    bad.write_text("not a model")
    with pytest.raises(DetectorError, match=r"text\.onnx: not a usable ONNX model"):
        OnnxTrunkDetector(bad)


def test_models_that_break_the_contract_are_named(tmp_path, constant_detector):
    with pytest.raises(DetectorError, match=r"outputs \['masks'\] missing"):
        OnnxTrunkDetector(_model(constant_detector, tmp_path / "a.onnx", outputs=("boxes", "labels", "scores", "segm")))
    with pytest.raises(DetectorError, match=r"input 'image' must have shape"):
        OnnxTrunkDetector(_model(constant_detector, tmp_path / "b.onnx", input_shape=[H, W]))
    with pytest.raises(DetectorError, match=r"input 'image' must be float32"):
        OnnxTrunkDetector(_model(constant_detector, tmp_path / "c.onnx", input_type=TensorProto.UINT8))


def test_an_image_of_the_wrong_type_is_named(tmp_path, constant_detector):
    det = OnnxTrunkDetector(_model(constant_detector, tmp_path / "m.onnx"))
    with pytest.raises(DetectorError, match=r"keyframe 7: expected an \(H, W, 3\) uint8 RGB image, got float32"):
        det.detect(np.zeros((H, W, 3), np.float32), where="keyframe 7")
    with pytest.raises(DetectorError, match="got uint8 \\(48, 64\\)"):
        det.detect(np.zeros((H, W), np.uint8))


def test_a_frame_of_another_aspect_is_letterboxed_not_stretched(tmp_path, constant_detector):
    # a portrait frame (96 x 32 px) into the 48 x 64 input: resized by 0.5 to 48 x 16 at the input's left, the
    # rest filled; a detection there maps back by the one scale (stretched, its x would have been halved again)
    m = np.zeros((1, 1, H, W), np.float32)
    m[0, 0, 10:40, 2:12] = 0.9
    values = {"boxes": np.array([[2, 10, 12, 40]], np.float32), "labels": np.array([CLASS_TRUNK], np.int64),
              "scores": np.array([0.9], np.float32), "masks": m}
    det = OnnxTrunkDetector(_model(constant_detector, tmp_path / "p.onnx", values=values))
    out = det.detect(np.zeros((2 * H, W // 2, 3), np.uint8))
    assert len(out) == 1
    np.testing.assert_allclose(out[0].box, [4, 20, 24, 80])
    v, u = np.nonzero(out[0].mask)
    assert out[0].mask.shape == (2 * H, W // 2)
    assert (v.min(), v.max(), u.min(), u.max()) == (20, 79, 4, 23)


def test_letterbox_keeps_the_aspect_and_fills_the_rest_with_the_frames_mean():
    from orchard_mapping.core.detection import letterbox

    frame = np.zeros((90, 160, 3), np.uint8)  # 16:9 into 4:3
    frame[:, :80] = 200
    x, scale = letterbox(frame, 48, 64)
    assert x.shape == (48, 64, 3) and scale == pytest.approx((0.4, 0.4))
    assert (x[:36, :32] == 200).all() and (x[:36, 32:] == 0).all()  # the frame, 0.4 of its size
    assert (x[36:] == 100).all()  # below it: its mean colour
    same, s2 = letterbox(np.full((96, 128, 3), 7, np.uint8), 48, 64)  # the input's own aspect: a plain resize
    assert same.shape == (48, 64, 3) and s2 == (0.5, 0.5) and (same == 7).all()
