"""The wide photometric jitter of detector training (orchard_mapping.train.detector): numpy and OpenCV only."""

import random

import numpy as np

from orchard_mapping.train.detector import _augment, _wide_colour


def _frame():
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)
    img[:, 70:90] = (120, 90, 60)  # a brown trunk
    masks = np.zeros((1, 120, 160), bool)
    masks[0, :, 70:90] = True
    return img, masks


def test_wide_jitter_moves_pixels_only_never_the_masks():
    img, masks = _frame()
    changed = 0
    for seed in range(60):
        out, out_masks = _augment(img, masks, random.Random(seed), wide=True)
        assert out.shape == img.shape and out.dtype == np.uint8
        flipped = not out_masks[0, 0, 70]
        assert np.array_equal(out_masks, masks[:, :, ::-1] if flipped else masks)
        trunk = out[:, 70:90] if not flipped else out[:, 70:90][:, ::-1]
        changed += int(np.abs(trunk.astype(int) - img[:, 70:90]).mean() > 3)
    assert changed >= 55


def test_wide_colour_turns_a_frame_grey_now_and_then_and_keeps_it_a_frame():
    img, _ = _frame()
    outs = [_wide_colour(img, random.Random(seed)) for seed in range(100)]
    assert all(o.shape == img.shape and o.dtype == np.uint8 for o in outs)
    grey = sum(int(np.array_equal(o[..., 0], o[..., 1]) and np.array_equal(o[..., 1], o[..., 2])) for o in outs)
    assert 3 <= grey <= 20  # 10 % grey frames, never most of them
    assert sum(int(not np.array_equal(o, img)) for o in outs) >= 70  # most frames get some other look


def test_narrow_jitter_is_the_shipped_models_and_draws_no_more_random_numbers():
    # the recipe of the shipped model (narrow) must stay reproducible: the wide branch draws after it
    img, masks = _frame()
    a, _ = _augment(img, masks, random.Random(3))
    b, _ = _augment(img, masks, random.Random(3), wide=False)
    assert np.array_equal(a, b)
