"""Fruit pixels and instances (core.fruit_pixels) with the shipped models, on frames rendered here from a
held-out seed, and on synthetic masks."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from orchard_mapping.core import fruit_pixels as fp
from orchard_mapping.train import fruit_pixels as tf

MODELS = Path(__file__).resolve().parents[3] / "models"
GMM = MODELS / "fruit_colour_gmm.json"
NET = MODELS / "fruit_net.onnx"


@pytest.fixture(scope="module")
def frames() -> list[tf.LabelledFrame]:
    """Two frames per side of a held-out seed (never trained or tuned on), mixed colours, standard look."""
    return tf.scene_frames(tf.HELDOUT_SEEDS[0], red_fraction=0.6, randomise=False, frames_per_side=2)


def _pixel_f1(model: fp.FruitPixelModel, frames: list[tf.LabelledFrame]) -> float:
    scores = [fp.score_frame(fp.segment_fruit(f.rgb, model), f.instances) for f in frames]
    tp = sum(s.true_positive for s in scores)
    return 2 * tp / max(sum(2 * s.true_positive + s.false_positive + s.false_negative for s in scores), 1)


def test_network_pixel_f1_on_held_out_frames(frames):
    assert sum(int((f.instances > 0).sum()) for f in frames) > 2000, "the frames must show fruit"
    f1 = _pixel_f1(fp.load_model(NET), frames)
    # 0.84 on these four frames, 0.85 over the benchmark's held-out standard-look mixed rows (docs/fruit.md)
    assert f1 > 0.75, f1


def test_network_finds_fruit_of_other_varieties_where_colour_alone_does_not():
    """Held-out frames of the randomised look with the varied fruit (blush over a green to golden ground,
    streaks): the network 0.85 on these four frames, the colour GMM 0.34 (fitted on saturated red and green)."""
    frames = tf.scene_frames(tf.HELDOUT_SEEDS[1], red_fraction=0.6, randomise=True, frames_per_side=2,
                             fruit_look="varied")
    assert sum(int((f.instances > 0).sum()) for f in frames) > 2000, "the frames must show fruit"
    net, gmm = _pixel_f1(fp.load_model(NET), frames), _pixel_f1(fp.load_model(GMM), frames)
    assert net > 0.75 and net > gmm + 0.3, (net, gmm)


def test_colour_gmm_on_red_fruit():
    """Red fruit against leaves, bark and soil: colour alone separates them (green fruit it does not)."""
    frames = tf.scene_frames(tf.HELDOUT_SEEDS[0], red_fraction=1.0, randomise=False, frames_per_side=2)
    f1 = _pixel_f1(fp.load_model(GMM), frames)
    assert f1 > 0.85, f1


def test_table_matches_direct_gmm_evaluation():
    model = fp.load_model(GMM)
    rgb = np.random.default_rng(0).integers(0, 256, (7, 9, 3), dtype=np.uint8)
    step = 256 // fp.LUT_LEVELS
    centre = ((rgb // step) * step + (step - 1) / 2).astype(np.float32) / 255  # the table's bin centres
    x = fp._colour(centre.reshape(-1, 3), model.space)
    direct = model.fruit.log_likelihood(x) - model.other.log_likelihood(x)
    np.testing.assert_allclose(fp.pixel_scores(rgb, model).ravel(), direct, rtol=1e-4, atol=1e-3)


def _discs(centres: list[tuple[int, int]], radius: int, shape=(80, 120)) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    for c in centres:
        cv2.circle(m, c, radius, 1, -1)
    return m.astype(bool)


def test_touching_discs_split_in_two():
    inst, n = fp.split_instances(_discs([(40, 40), (68, 40)], 15))  # centres 28 px apart, radius 15: they overlap
    assert n == 2
    assert inst[40, 40] != inst[40, 68] and min(inst[40, 40], inst[40, 68]) > 0
    sizes = np.bincount(inst.ravel())[1:]
    assert sizes.min() > 0.4 * sizes.max()  # cut near the neck, not a sliver


def test_one_disc_and_a_speck():
    m = _discs([(40, 40)], 12)
    m[5, 100] = True  # below min_area_px
    inst, n = fp.split_instances(m)
    assert n == 1 and inst[5, 100] == 0 and np.all(inst[m & (inst > 0)] == 1)


def test_components_without_splitting():
    inst, n = fp.split_instances(_discs([(40, 40), (68, 40)], 15), fp.FruitMaskParams(split="none"))
    assert n == 1


def test_score_frame_counts_matches():
    truth = np.zeros((80, 120), np.int32)
    truth[_discs([(30, 40)], 10)] = 5
    truth[_discs([(90, 40)], 10)] = 9
    truth[2:4, 2:4] = 3  # 4 px: below min_pixels, not counted
    inst = np.where(truth == 5, 1, 0).astype(np.int32)
    s = fp.score_frame(fp.FruitMask(inst > 0, inst, 1), truth)
    assert (s.true_instances, s.found, s.predicted, s.matched_predictions) == (2, 1, 1, 1)
    assert s.false_positive == 0 and s.false_negative == int(np.count_nonzero(truth)) - s.true_positive


@pytest.mark.parametrize("bad", [np.zeros((4, 4), np.uint8), np.zeros((4, 4, 4), np.uint8),
                                 np.zeros((4, 4, 3), np.float32), [[0, 0, 0]]])
def test_bad_image_raises(bad):
    with pytest.raises(fp.FruitImageError):
        fp.segment_fruit(bad, fp.load_model(GMM))


def test_bad_model_files_raise(tmp_path):
    with pytest.raises(fp.FruitModelError, match="not found"):
        fp.load_model(tmp_path / "missing.onnx")
    (tmp_path / "x.json").write_text(json.dumps({"schema": "other"}))
    with pytest.raises(fp.FruitModelError, match="schema"):
        fp.load_model(tmp_path / "x.json")
    doc = json.loads(GMM.read_text())
    doc["space"] = "xyz"
    (tmp_path / "y.json").write_text(json.dumps(doc))
    with pytest.raises(fp.FruitModelError, match="colour space"):
        fp.load_model(tmp_path / "y.json")
