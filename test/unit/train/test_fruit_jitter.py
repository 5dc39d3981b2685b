"""The photometric jitter of the fruit network's training crops (orchard_mapping.train.fruit_pixels):
numpy and OpenCV only."""

import numpy as np

from orchard_mapping.train.fruit_pixels import photometric_jitter


def _crop() -> np.ndarray:
    img = np.full((64, 64, 3), 0.5, np.float32)  # grey
    img[16:48, 16:48] = (0.75, 0.1, 0.08)  # a saturated red fruit
    img[:, :8] = (0.2, 0.5, 0.1)  # a leaf
    return img


def _saturation(rgb: np.ndarray) -> float:
    """HSV saturation: (max - min) / max, whatever the exposure."""
    return float((rgb.max() - rgb.min()) / max(rgb.max(), 1e-6))


def test_wide_jitter_washes_colours_out_and_turns_hue_but_keeps_fruit_apart_from_leaves():
    img = _crop()
    sats, redder = [], 0
    for seed in range(200):
        out = photometric_jitter(img.copy(), np.random.default_rng(seed), "wide")
        assert out.shape == img.shape and out.dtype == np.float32 and 0.0 <= out.min() and out.max() <= 1.0
        fruit, leaf = out[20:44, 20:44].mean(axis=(0, 1)), out[:, :6].mean(axis=(0, 1))
        sats.append(_saturation(fruit) / _saturation(img[32, 32]))
        redder += (fruit[0] - fruit[1]) > (leaf[0] - leaf[1])  # the fruit stays the redder of the two
    sats = np.array(sats)
    assert (sats < 0.6).mean() > 0.15  # washed-out fruit, as a tone curve or haze shows them
    assert (sats > 0.95).mean() > 0.2  # and saturated ones still
    assert redder == 200


def test_narrow_jitter_keeps_the_look_close_and_both_are_seeded():
    img = _crop()
    for seed in range(50):
        a = photometric_jitter(img.copy(), np.random.default_rng(seed), "narrow")
        b = photometric_jitter(img.copy(), np.random.default_rng(seed), "narrow")
        assert np.array_equal(a, b)
        assert 0.75 < _saturation(a[32, 32]) / _saturation(img[32, 32]) < 1.25
    w1 = photometric_jitter(img.copy(), np.random.default_rng(7), "wide")
    w2 = photometric_jitter(img.copy(), np.random.default_rng(7), "wide")
    assert np.array_equal(w1, w2)
