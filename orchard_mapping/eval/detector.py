"""Mask AP of an ONNX trunk detector on COCO folders (pycocotools' COCOeval, segm)."""

from __future__ import annotations

import contextlib
import copy
import io
import re
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from orchard_mapping.core.detection import CLASS_NAMES, OnnxTrunkDetector
from orchard_mapping.io.coco import load_coco, mask_rle, solid_outline

__all__ = ["DetectorScores", "bootstrap_intervals", "evaluate_detector", "recording_of"]


@dataclass(frozen=True)
class DetectorScores:
    images: int
    instances: int  # annotated trunks and posts (not counting regions to ignore, COCO iscrowd)
    ap: float  # mask AP over IoU 0.50:0.95 (COCO)
    ap50: float
    ap75: float
    ap_trunk: float  # per class, IoU 0.50:0.95 (-1: no instance of that class)
    ap_post: float
    ms_per_image: float  # median onnxruntime + post-processing time
    ap50_trunk: float  # per class at IoU 0.50
    ap50_post: float
    # COCO's sizes (mask area < 32^2, 32^2-96^2, > 96^2 px), IoU 0.50:0.95, both classes (-1: none of that size).
    # A trunk behind leaves or weeds is a sliver: where a model loses AP shows here.
    ap_small: float
    ap_medium: float
    ap_large: float
    # AP50 with the class ignored: a trunk found but called a post counts. Against ap50: what the
    # confusion of the two classes costs.
    ap50_any_class: float
    ignored: int = 0  # regions to ignore (iscrowd 1): scattered trunk pixels seen through leaves, io/coco.py
    solid_outlines: bool = False  # instances scored as their solid outlines (io.coco.solid_outline)
    # With bootstrap draws: 95 % percentile intervals of ap, ap50 and ap50_trunk over that many resamplings of
    # the recordings (bootstrap_intervals); None without.
    bootstrap: int = 0
    recordings: int = 0  # recordings the frames were resampled by (recording_of)
    ap_interval: tuple[float, float] | None = None
    ap50_interval: tuple[float, float] | None = None
    ap50_trunk_interval: tuple[float, float] | None = None

def evaluate_detector(model: str | Path, data: list[Path], threads: int = 2, *,
                      ignore_crowd: bool = True, solid_outlines: bool = False, bootstrap: int = 0,
                      flip: bool = False) -> DetectorScores:
    """Scores of `model` on the COCO folders `data`. `ignore_crowd=False` scores regions to ignore (iscrowd)
    as instances that must be found, as COCO folders exported before the flag existed did.
    `solid_outlines=True` scores each instance (not the regions to ignore) as its solid outline, without the
    specks of a trunk seen through leaves beside its bark: what an annotator outlines.
    `flip=True` runs the detector with its test-time flip (trunks.flip_test).
    `bootstrap=N` adds 95 % intervals of AP, AP50 and trunk AP50 over N resamplings of the recordings."""
    from pycocotools import mask as mask_util
    from pycocotools.coco import COCO

    det = OnnxTrunkDetector(model, score_threshold=0.05, threads=threads, flip=flip)
    images, anns, results, times = [], [], [], []
    for folder in data:
        for im in load_coco(folder):
            img_id = len(images) + 1
            images.append({"id": img_id, "width": im.width, "height": im.height, "file_name": str(im.path)})
            for c, m, crowd in zip(im.classes, im.masks, im.crowd, strict=True):
                if solid_outlines and not crowd:
                    m = solid_outline(m, or_whole=True)
                rle = mask_rle(m)
                anns.append({"id": len(anns) + 1, "image_id": img_id, "category_id": int(c), "segmentation": rle,
                             "area": float(m.sum()), "bbox": list(mask_util.toBbox(rle)),
                             "iscrowd": int(crowd and ignore_crowd)})
            rgb = cv2.cvtColor(cv2.imread(str(im.path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
            t0 = time.perf_counter()
            found = det.detect(rgb, where=str(im.path))
            times.append(time.perf_counter() - t0)
            for d in found:
                rle = mask_rle(d.mask)
                results.append({"image_id": img_id, "category_id": d.class_id, "segmentation": rle,
                                "score": d.score})
    gt = COCO()
    gt.dataset = {"images": images, "annotations": anns,
                  "categories": [{"id": k, "name": v} for k, v in sorted(CLASS_NAMES.items())]}
    with contextlib.redirect_stdout(io.StringIO()):
        gt.createIndex()
        dt = gt.loadRes(results) if results else COCO()
        ev = coco_eval(gt, dt, use_categories=True)
        agnostic = coco_eval(gt, dt, use_categories=False)
    precision = ev.eval["precision"]  # (T, R, K, A, M): IoU thresholds, recall, class, area, max dets

    def class_ap(k: int, iou: slice = slice(None)) -> float:
        return _mean_valid(precision[iou, :, k, 0, -1])

    at50 = slice(0, 1)  # iouThrs[0] == 0.5
    ignored = sum(a["iscrowd"] for a in anns)
    intervals: dict[str, object] = {}
    if bootstrap > 0:
        groups = [recording_of(Path(im["file_name"])) for im in images]
        intervals = dict(bootstrap=bootstrap, recordings=len(set(groups)),
                         **bootstrap_intervals(ev, groups, bootstrap))
    return DetectorScores(len(images), len(anns) - ignored, float(ev.stats[0]), float(ev.stats[1]), float(ev.stats[2]),
                          class_ap(0), class_ap(1), float(np.median(times)) * 1000 if times else float("nan"),
                          ap50_trunk=class_ap(0, at50), ap50_post=class_ap(1, at50), ap_small=float(ev.stats[3]),
                          ap_medium=float(ev.stats[4]), ap_large=float(ev.stats[5]),
                          ap50_any_class=float(agnostic.stats[1]), ignored=ignored, solid_outlines=solid_outlines,
                          **intervals)  # type: ignore[arg-type]


_FRAME_NUMBER = re.compile(r"[_-]?\d+$")


def recording_of(path: Path) -> str:
    """The recording a frame belongs to: its folder and file name without the trailing frame number
    (images/scene0007_front_000013.jpg -> images/scene0007_front). A name without one is a recording of its own."""
    stem = _FRAME_NUMBER.sub("", path.stem) or path.stem
    return str(path.parent / stem)


def bootstrap_intervals(ev, groups: list[str], draws: int, seed: int = 0,
                        level: float = 0.95) -> dict[str, tuple[float, float]]:
    """Percentile intervals of mask AP, AP50 and trunk AP50 over `draws` resamplings, with replacement, of the
    recordings `groups` (one per image of an evaluated, class-aware COCOeval `ev`, in its image order).

    Recordings, not frames, are drawn: frames of one pass see the same trees from a few cm apart, so drawing
    frames would make the interval too narrow. Each draw re-accumulates COCOeval's per-image matches (the
    matching is not redone), over all areas at 100 detections."""
    pe = ev._paramsEval
    n_img, n_area = len(pe.imgIds), len(pe.areaRng)
    n_cat = len(pe.catIds) if pe.useCats else 1
    if len(groups) != n_img:
        raise ValueError(f"{len(groups)} recording names for {n_img} evaluated images")
    names, member_of = np.unique(np.asarray(groups), return_inverse=True)
    members = [np.flatnonzero(member_of == g) for g in range(len(names))]
    p = copy.deepcopy(pe)
    p.areaRng, p.areaRngLbl, p.maxDets = [pe.areaRng[0]], [pe.areaRngLbl[0]], [pe.maxDets[-1]]
    rng = np.random.default_rng(seed)
    draws_out = np.empty((draws, 3))  # (draws, [AP, AP50, trunk AP50])
    for b in range(draws):
        idx = np.concatenate([members[g] for g in rng.integers(len(names), size=len(names))])  # (I',)
        e = copy.copy(ev)
        e._paramsEval = copy.copy(pe)
        e._paramsEval.imgIds = list(range(len(idx)))
        p.imgIds = e._paramsEval.imgIds
        # COCOeval's layout: evalImgs[k * A * I + a * I + i]; only area "all" (a = 0) is accumulated
        e.evalImgs = [None] * (n_cat * n_area * len(idx))
        for k in range(n_cat):
            for j, i in enumerate(idx):
                e.evalImgs[k * n_area * len(idx) + j] = ev.evalImgs[k * n_area * n_img + i]
        with contextlib.redirect_stdout(io.StringIO()):
            e.accumulate(p)
        prec = e.eval["precision"][:, :, :, 0, 0]  # (T, R, K)
        draws_out[b] = [_mean_valid(prec), _mean_valid(prec[0]), _mean_valid(prec[0, :, 0])]
    lo, hi = np.percentile(draws_out, [50 * (1 - level), 50 * (1 + level)], axis=0)
    return {name: (float(lo[c]), float(hi[c])) for c, name in
            enumerate(("ap_interval", "ap50_interval", "ap50_trunk_interval"))}


def _mean_valid(p: np.ndarray) -> float:
    """COCO's summary: the mean of the precisions that exist (-1: no instance of that class in the draw)."""
    v = p[p > -1]
    return float(v.mean()) if v.size else -1.0


def coco_eval(gt, dt, use_categories: bool):
    """pycocotools' COCOeval (segm), evaluated, accumulated and summarised (stats filled)."""
    from pycocotools.cocoeval import COCOeval

    ev = COCOeval(gt, dt, "segm")
    ev.params.useCats = int(use_categories)
    ev.evaluate()
    ev.accumulate()
    ev.summarize()
    return ev
