"""COCO instances (io/coco.py): which visible parts of a trunk count as instances, and iscrowd read back.

An annotator outlines a trunk where a solid part of its bark is in view; pixels of a trunk scattered
between leaves are a region to ignore (COCO iscrowd), not an instance a detector must find.
"""

from __future__ import annotations

import json

import cv2
import numpy as np

from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK
from orchard_mapping.io.coco import MIN_SOLID_PIXELS, SOLID_PX, load_coco, mask_rle, recognisable, solid_outline

H, W = 240, 320


def _strip(width: int, height: int = 120) -> np.ndarray:
    m = np.zeros((H, W), bool)
    m[60:60 + height, 100:100 + width] = True
    return m


def test_a_solid_strip_of_bark_is_recognisable_and_scattered_pixels_are_not():
    strip = _strip(12)  # 1440 px: a trunk's strip above the weeds
    assert recognisable(strip)
    # the same trunk seen through gaps between leaves: as many pixels, in specks of 2 x 2
    rng = np.random.default_rng(0)
    specks = np.zeros((H, W), bool)
    for v, u in zip(rng.integers(0, H - 2, 400), rng.integers(0, W - 2, 400), strict=True):
        specks[v:v + 2, u:u + 2] = True
    assert specks.sum() > strip.sum() and not recognisable(specks)
    # a strip narrower than SOLID_PX (a trunk behind a fence of leaf edges) has no solid part
    assert not recognisable(_strip(SOLID_PX - 2, height=400 // 2))
    # a solid part, but smaller than the limit
    small = _strip(10, height=MIN_SOLID_PIXELS // 10 - 2)
    assert not recognisable(small) and recognisable(_strip(10, height=MIN_SOLID_PIXELS // 10 + 2))
    # two solid parts of 300 px do not add up to one recognisable part
    two = _strip(10, height=30)
    two[160:190, 200:210] = True
    assert not recognisable(two)


def test_the_solid_outline_keeps_the_bark_strip_whole_and_drops_the_specks_seen_through_leaves():
    # a trunk's strip of bark at its foot, 14 px wide with a ragged edge, and its specks up through the canopy
    strip = _strip(14, height=60)
    strip[60:120:3, 99] = True  # one-pixel notches on the edge belong to the strip's outline
    specks = np.zeros((H, W), bool)
    specks[10:58:6, 104:106] = True  # 2 x 2 specks above the strip, within the trunk's line
    outline = solid_outline(strip | specks)
    assert (outline == strip).all()
    # the instance's box was 3.6 times as tall as its outline's
    rows = np.nonzero((strip | specks).any(axis=1))[0]
    assert (rows.max() - rows.min() + 1) > 1.5 * 60
    # a strip with no solid part has no outline; training and scoring keep such an annotator's sliver whole
    assert not solid_outline(_strip(SOLID_PX - 2)).any()
    assert (solid_outline(_strip(SOLID_PX - 2), or_whole=True) == _strip(SOLID_PX - 2)).all()


def test_iscrowd_comes_back_from_the_file_polygons_and_rle_alike(tmp_path):
    cv2.imwrite(str(tmp_path / "f.png"), np.zeros((H, W, 3), np.uint8))
    rle = mask_rle(_strip(12))
    anns = [
        {"id": 1, "image_id": 1, "category_id": 1, "iscrowd": 0,
         "segmentation": {"size": rle["size"], "counts": rle["counts"].decode("ascii")}},
        {"id": 2, "image_id": 1, "category_id": 2, "iscrowd": 1,
         "segmentation": [[200.0, 20.0, 230.0, 20.0, 230.0, 200.0, 200.0, 200.0]]},
        {"id": 3, "image_id": 1, "category_id": 1,  # no iscrowd key: an instance, as COCO reads it
         "segmentation": [[10.0, 10.0, 40.0, 10.0, 40.0, 90.0, 10.0, 90.0]]},
    ]
    doc = {"images": [{"id": 1, "file_name": "f.png", "width": W, "height": H}], "annotations": anns,
           "categories": [{"id": 1, "name": "trunk"}, {"id": 2, "name": "Post"}]}
    (tmp_path / "instances.json").write_text(json.dumps(doc))
    (im,) = load_coco(tmp_path)
    assert im.classes.tolist() == [CLASS_TRUNK, CLASS_POST, CLASS_TRUNK]
    assert im.crowd.tolist() == [False, True, False]
    assert im.masks[1, 100, 215] and not im.masks[1, 100, 100]
