"""COCO instance annotations: the detector's training and evaluation data.

A COCO folder holds `instances.json` (the COCO "instances" format that
annotation tools such as the VGG Image Annotator or CVAT export: images,
annotations with polygon or RLE segmentation, categories) and the images it
names, relative to the folder. `export_coco` turns a simulator output (bags +
16-bit instance masks) into one; `load_coco` reads any, with typed errors.
Categories are matched by name: "trunk" and "post" (others are ignored).

COCO's `iscrowd: 1` marks a region to ignore: COCOeval neither rewards nor
penalises a detection on it, and training does not take it as an instance.
`export_coco` sets it on what no annotator would outline as a trunk or post:
scattered pixels of a trunk seen through gaps between leaves or weeds
(`recognisable`). The paper's real frames were annotated by people, who label
a trunk where a solid part of its bark is in view.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from orchard_mapping.core.detection import CLASS_NAMES, CLASS_POST, CLASS_TRUNK, DetectorError
from orchard_mapping.io.results import atomic_write_json

__all__ = ["CocoImage", "export_coco", "load_coco", "mask_rle", "recognisable", "solid_outline"]

MIN_INSTANCE_PIXELS = 30  # slivers at the image border teach nothing
# A recognisable instance has a solid part (every pixel inside a SOLID_PX square of the object's pixels) of
# at least MIN_SOLID_PIXELS. Measured on held-out slope_weeds frames (640x480): trunk instances under 200 px
# have a median solid part of 0 px, those over 1000 px keep 87-96 % of their pixels solid (10th percentile
# of the largest solid part: 1033 px), so the limit sits between fragments seen through leaves and the
# smallest strip of bark above the weeds.
SOLID_PX = 5
MIN_SOLID_PIXELS = 500


@dataclass(frozen=True)
class CocoImage:
    path: Path
    width: int
    height: int
    classes: np.ndarray  # (N,) int: CLASS_TRUNK / CLASS_POST
    masks: np.ndarray  # (N, H, W) bool
    crowd: np.ndarray  # (N,) bool: COCO iscrowd, a region to ignore (neither a miss nor a false detection)


_SQUARE = cv2.getStructuringElement(cv2.MORPH_RECT, (SOLID_PX, SOLID_PX))


def _solid_part(mask: np.ndarray) -> np.ndarray:
    """(H, W) uint8: the pixels inside a SOLID_PX square of the mask's pixels (a morphological opening)."""
    return cv2.morphologyEx(np.asarray(mask, np.uint8), cv2.MORPH_OPEN, _SQUARE)


def recognisable(mask: np.ndarray) -> bool:
    """Whether an annotator would outline this visible part of a trunk or post: a connected solid part of
    at least MIN_SOLID_PIXELS (opened with a SOLID_PX square), not pixels scattered between leaves."""
    solid = _solid_part(mask)
    if int(solid.sum()) < MIN_SOLID_PIXELS:
        return False
    n, _, stats, _ = cv2.connectedComponentsWithStats(solid, connectivity=8)
    return bool(stats[1:, cv2.CC_STAT_AREA].max() >= MIN_SOLID_PIXELS)  # n > 1: solid has pixels


def solid_outline(mask: np.ndarray, *, or_whole: bool = False) -> np.ndarray:
    """(H, W) bool: what an annotator outlines of an instance: its solid parts with their edges (within
    SOLID_PX of them), without the specks of the same trunk seen through leaves above or beside them.
    `or_whole`: an instance without a solid part (an annotator's thin sliver in a COCO folder) is returned
    whole rather than empty.

    The detector is trained on these. Trained on whole masks, a trunk's box reached from its bark at the
    foot up through the canopy to its highest speck (on held-out slope_weeds frames 48 % of trunk boxes
    were over 25 % taller than their solid part's), and the model learnt to box canopies."""
    m = np.asarray(mask, np.uint8)
    outline = (m & cv2.dilate(_solid_part(m), _SQUARE)).astype(bool)
    return outline if outline.any() or not or_whole else m.astype(bool)


def mask_rle(mask: np.ndarray) -> dict:
    """COCO compressed RLE of a boolean mask (H, W); `counts` as bytes (pycocotools' own form)."""
    from pycocotools import mask as mask_util

    return mask_util.encode(np.asfortranarray(np.asarray(mask, np.uint8)))


def export_coco(sim_dir: str | Path, out_dir: str | Path, *, every: int = 5,
                sides: tuple[str, ...] = ("front", "back")) -> Path:
    """Write every `every`-th masked frame of a simulation as JPEG + instances.json; returns its path.

    An instance that is not `recognisable` is written with iscrowd 1 (a region to ignore)."""
    from orchard_mapping.io.bags import read_rgbd
    from orchard_mapping.io.masks import MaskFolderDetector

    sim_dir, out_dir = Path(sim_dir), Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    images, annotations = [], []
    for side in sides:
        masks = MaskFolderDetector(sim_dir / "masks", side)
        if not len(masks.stamps):
            continue
        for n, frame in enumerate(read_rgbd(sim_dir / side)):
            if n % every:
                continue
            dets = masks.detect_at(frame.stamp)
            name = f"images/{sim_dir.name}_{side}_{frame.index:06d}.jpg"
            bgr = cv2.cvtColor(frame.color, cv2.COLOR_RGB2BGR)
            if not cv2.imwrite(str(out_dir / name), bgr, [cv2.IMWRITE_JPEG_QUALITY, 95]):
                raise OSError(f"could not write {out_dir / name}")
            img_id = len(images) + 1
            h, w = frame.color.shape[:2]
            images.append({"id": img_id, "file_name": name, "width": w, "height": h})
            for d in dets:
                area = int(d.mask.sum())
                if area < MIN_INSTANCE_PIXELS:
                    continue
                rle = mask_rle(d.mask)
                rle["counts"] = rle["counts"].decode("ascii")  # JSON
                x1, y1, x2, y2 = (float(v) for v in d.box)
                annotations.append({"id": len(annotations) + 1, "image_id": img_id, "category_id": d.class_id,
                                    "segmentation": rle, "area": area, "bbox": [x1, y1, x2 - x1, y2 - y1],
                                    "iscrowd": int(not recognisable(d.mask))})
    doc = {"images": images, "annotations": annotations,
           "categories": [{"id": k, "name": v} for k, v in sorted(CLASS_NAMES.items())],
           "info": {"description": f"orchard_mapping simulator frames from {sim_dir}", "every": every}}
    return atomic_write_json(out_dir / "instances.json", doc)


def _fail(path: Path, msg: str) -> DetectorError:
    return DetectorError(f"COCO annotations {path}: {msg}")


def load_coco(folder: str | Path) -> list[CocoImage]:
    """Images with their trunk and post instance masks (decoded from polygons or RLE)."""
    from pycocotools import mask as mask_util

    folder = Path(folder)
    path = folder / "instances.json" if folder.is_dir() else folder
    root = path.parent
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise _fail(path, "not found") from err
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise _fail(path, f"not readable JSON ({err})") from err
    try:
        names = {int(c["id"]): str(c["name"]).lower() for c in doc["categories"]}
        to_class = {cid: {"trunk": CLASS_TRUNK, "post": CLASS_POST}[n] for cid, n in names.items()
                    if n in ("trunk", "post")}
        by_image: dict[int, list[dict]] = {}
        for a in doc["annotations"]:
            by_image.setdefault(int(a["image_id"]), []).append(a)
        out = []
        for im in doc["images"]:
            h, w = int(im["height"]), int(im["width"])
            cls, masks, crowd = [], [], []
            for a in by_image.get(int(im["id"]), []):
                if int(a["category_id"]) not in to_class:
                    continue
                seg = a["segmentation"]
                if isinstance(seg, list):  # polygons
                    rle = mask_util.merge(mask_util.frPyObjects(seg, h, w))
                elif isinstance(seg, dict) and isinstance(seg.get("counts"), list):  # uncompressed RLE
                    rle = mask_util.frPyObjects(seg, h, w)
                else:
                    rle = dict(seg)
                    if isinstance(rle["counts"], str):
                        rle["counts"] = rle["counts"].encode("ascii")
                m = mask_util.decode(rle).astype(bool)
                if m.sum() >= MIN_INSTANCE_PIXELS:
                    cls.append(to_class[int(a["category_id"])])
                    masks.append(m)
                    crowd.append(bool(a.get("iscrowd", 0)))
            out.append(CocoImage(root / im["file_name"], w, h, np.asarray(cls, int),
                                 np.asarray(masks, bool).reshape(-1, h, w), np.asarray(crowd, bool)))
    except (KeyError, TypeError, ValueError) as err:
        raise _fail(path, f"not in the COCO instances format ({type(err).__name__}: {err})") from err
    return out
