"""Re-exporting trained weights with other inference settings (orchard_mapping.train.detector.reexport,
`orchard-map export-detector`). The record checks run without torch; the export itself only where the
training extra (torch, torchvision) is installed."""

import json

import pytest

from orchard_mapping.train.detector import TrainSettings, reexport


def test_a_missing_record_is_named(tmp_path):
    with pytest.raises(ValueError, match=r"training record .*nothing\.json"):
        reexport(tmp_path / "w.pt", tmp_path / "m.onnx", tmp_path / "nothing.json")


def test_a_widest_aspect_takes_the_records_short_side_and_is_checked(tmp_path):
    # --max-aspect without --min-size: the record is read once, by reexport, and a missing one is named there
    with pytest.raises(ValueError, match=r"training record .*w\.json"):
        reexport(tmp_path / "w.pt", tmp_path / "m.onnx", max_aspect=16 / 9)
    (tmp_path / "w.json").write_text(json.dumps({"settings": {"min_size": 416}}))
    with pytest.raises(ValueError, match="aspect .* 1 to 4, got 5.0"):
        reexport(tmp_path / "w.pt", tmp_path / "m.onnx", max_aspect=5.0)
    assert not (tmp_path / "m.onnx").exists()


def test_a_record_without_settings_is_refused(tmp_path):
    rec = tmp_path / "w.json"
    rec.write_text(json.dumps({"images": 3}))
    with pytest.raises(ValueError, match="not readable as a train-detector record"):
        reexport(tmp_path / "w.pt", tmp_path / "m.onnx")


def test_unknown_settings_are_named(tmp_path):
    rec = tmp_path / "w.json"
    rec.write_text(json.dumps({"settings": {"min_size": 416, "anchor_sizes": [16]}}))
    with pytest.raises(ValueError, match="anchor_sizes"):
        reexport(tmp_path / "w.pt", tmp_path / "m.onnx")
    with pytest.raises(ValueError, match="rpn_pre_nms"):
        reexport(tmp_path / "w.pt", tmp_path / "m.onnx", rpn_pre_nms=600)
    assert not (tmp_path / "m.onnx").exists()


def test_reexport_bakes_the_new_settings_into_the_model(tmp_path):
    pytest.importorskip("torch")
    pytest.importorskip("torchvision")
    onnx = pytest.importorskip("onnx")
    from dataclasses import asdict

    from orchard_mapping.train.detector import build_model, save_checkpoint

    s = TrainSettings(min_size=128, max_size=171, fpn_channels=16, representation=32)
    save_checkpoint(build_model(s), tmp_path / "w.pt")
    (tmp_path / "w.json").write_text(json.dumps({"settings": asdict(s), "images": 7}))
    card = reexport(tmp_path / "w.pt", tmp_path / "m.onnx", rpn_pre_nms_test=50, rpn_post_nms_test=20)
    assert card["settings"]["rpn_pre_nms_test"] == 50 and card["images"] == 7
    assert json.loads((tmp_path / "m.json").read_text())["settings"]["rpn_post_nms_test"] == 20
    model = onnx.load(str(tmp_path / "m.onnx"))
    assert [i.name for i in model.graph.input] == ["image"]
    dims = model.graph.input[0].type.tensor_type.shape.dim
    assert dims[0].dim_value == 3 and not dims[1].dim_value and not dims[2].dim_value  # height, width free
    reexport(tmp_path / "w.pt", tmp_path / "f.onnx", dynamic_input=False)
    fixed = onnx.load(str(tmp_path / "f.onnx")).graph.input[0].type.tensor_type.shape.dim
    assert [d.dim_value for d in fixed] == [3, 480, 640]
