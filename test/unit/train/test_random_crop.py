"""The training crop (orchard_mapping.train.detector.random_crop): numpy only, so it runs without torch."""

import random

import numpy as np

from orchard_mapping.train.detector import CROP_MIN_AREA_PX, random_crop


def _frame():
    # each pixel holds its own row and column, so a crop's window can be read back from its pixels
    rows, cols = np.mgrid[0:480, 0:640]
    img = np.stack([rows, cols, np.zeros_like(rows)], axis=2).astype(np.int32)  # (480, 640, 3)
    masks = np.zeros((3, 480, 640), bool)
    masks[0, 200:280, 300:330] = True  # a trunk in the middle: inside every window of 0.6 or more
    masks[1, 0:480, 0:6] = True  # a strip at the left edge: kept or dropped by where the window falls
    masks[2, 470:480, 630:634] = True  # 40 px in the corner
    return img, masks


def test_crop_keeps_the_aspect_the_pixels_and_the_instances_left_in_the_window():
    img, masks = _frame()
    strip_kept = []
    for seed in range(200):
        out, kept_masks, kept = random_crop(img, masks, random.Random(seed), 0.6)
        h, w = out.shape[:2]
        assert 0.6 * 480 - 1 <= h <= 480 and abs(w / h - 640 / 480) < 0.01
        y0, x0 = int(out[0, 0, 0]), int(out[0, 0, 1])
        assert np.array_equal(out, img[y0:y0 + h, x0:x0 + w])
        assert kept[0], f"seed {seed}: the middle trunk was dropped"
        assert kept_masks.shape == (int(kept.sum()), h, w)
        assert np.array_equal(kept_masks, masks[kept][:, y0:y0 + h, x0:x0 + w])
        assert all(m.sum() >= CROP_MIN_AREA_PX for m in kept_masks)
        assert kept_masks[0].sum() == 80 * 30
        assert kept[1] == (x0 < 6)  # the strip is 480 x 6 px: any part of it in the window is over 40 px
        strip_kept.append(bool(kept[1]))
    assert any(strip_kept) and not all(strip_kept)


def test_crop_that_would_leave_no_instance_returns_the_whole_frame():
    img = np.zeros((480, 640, 3), np.uint8)
    masks = np.zeros((1, 480, 640), bool)
    masks[0, 0:10, 0:10] = True  # 100 px in one corner; most windows miss it
    whole = 0
    for seed in range(50):
        out, kept_masks, kept = random_crop(img, masks, random.Random(seed), 0.6)
        assert kept.all() and kept_masks[0].sum() >= CROP_MIN_AREA_PX
        whole += out.shape == img.shape
    assert whole > 0
