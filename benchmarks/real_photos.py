"""Benchmark on an unseen domain: real photographs of orchard trees (benchmarks/data/real_photos/).

Never used for training or tuning. Runs the shipped trunk detector as `orchard-map run` builds it
(OnnxTrunkDetector.from_params of the config's `trunks` section: default score threshold 0.5) on every frame of
every source and prints one table:

  frames          frames of the source
  true trunks     annotated trunks ("mask" sources: instance masks; "box" sources: boxes; "caliper": the one
                  measured tree per frame)
  found trunk     true trunks matched by a detection labelled trunk: mask IoU >= 0.5 where masks exist, box IoU
                  >= 0.5 where only boxes do; greedy by score, one detection per trunk. Caliper sources have no
                  outline: a detection counts when its mask is centred within 15 % of the width of the image's
                  centre column and at least 20 % of the image tall (the measured tree is the one nearest the
                  centre, the source's own rule)
  found any       the same, the detection labelled trunk or post
  false/frame     detections labelled trunk matched to no true trunk, per frame (n/a for caliper sources, whose
                  other trees are not annotated)
  ms              median detector time per frame (resizing, onnxruntime, post-processing)
  diam MAE/bias   caliper sources with depth: the matched detection's diameter, median mask width (px) over its
                  middle rows x median depth on the mask / fx, against the caliper (mm)

Usage:
  python benchmarks/real_photos.py [--data benchmarks/data/real_photos] [--sources NAME ...]
        [--set trunks.flip_test=true] [--set trunks.score_threshold=0.3] [--json out.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import cv2
import numpy as np

from orchard_mapping.config import load_config, parse_sets, unflatten
from orchard_mapping.core.detection import CLASS_POST, CLASS_TRUNK, Detection, OnnxTrunkDetector
from orchard_mapping.io.results import portable_json

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "benchmarks" / "data" / "real_photos"
IOU_THRESHOLD = 0.5
CENTRE_BAND = 0.15  # caliper sources: |mask centre column - W/2| <= this x W
MIN_HEIGHT = 0.20  # caliper sources: mask rows >= this x H


@dataclass
class FrameMatch:
    """What one frame's detections found of its annotated trunks."""

    true_trunks: int
    found_trunk: int  # matched by a detection labelled trunk
    found_any: int  # matched by a detection labelled trunk or post
    false_trunks: int  # detections labelled trunk matched to no true trunk


def _iou(gt: Sequence[np.ndarray], dets: Sequence[np.ndarray], kind: str) -> np.ndarray:
    """(G, D) IoU of true trunks and detections: masks (H, W) bool, or boxes (4,) x1 y1 x2 y2 (pycocotools)."""
    from pycocotools import mask as mask_util

    if not len(gt) or not len(dets):
        return np.zeros((len(gt), len(dets)))
    if kind == "mask":
        enc = [mask_util.encode(np.asfortranarray(np.asarray(m, np.uint8))) for m in (*gt, *dets)]
        g, d = enc[:len(gt)], enc[len(gt):]
    else:
        g = [[b[0], b[1], b[2] - b[0], b[3] - b[1]] for b in np.asarray(gt, float)]
        d = [[b[0], b[1], b[2] - b[0], b[3] - b[1]] for b in np.asarray(dets, float)]
    # pycocotools' iou(dt, gt, iscrowd): (D, G)
    return np.asarray(mask_util.iou(d, g, [0] * len(g)), float).reshape(len(d), len(g)).T


def _greedy(iou: np.ndarray, order: Sequence[int], threshold: float) -> dict[int, int]:
    """Detections (column indices, in `order`) each take the free true trunk they overlap most, if >= threshold;
    {detection: true trunk}."""
    taken: set[int] = set()
    out = {}
    for j in order:
        best, best_iou = -1, threshold
        for i in range(iou.shape[0]):
            if i not in taken and iou[i, j] >= best_iou:
                best, best_iou = i, iou[i, j]
        if best >= 0:
            taken.add(best)
            out[j] = best
    return out


def match_frame(gt: Sequence[np.ndarray], dets: Sequence[Detection], kind: str = "mask",
                threshold: float = IOU_THRESHOLD) -> FrameMatch:
    """Match one frame's detections to its true trunks (`gt`: masks (H, W) bool, or boxes x1 y1 x2 y2 when
    `kind` is "box"), as COCO does: by score, each detection to the free trunk it overlaps most, IoU >= threshold.
    "trunk" counts detections labelled trunk only; "any" those labelled trunk or post."""
    cand = [d.mask if kind == "mask" else d.box for d in dets]
    iou = _iou(gt, cand, kind)
    by_score = sorted(range(len(dets)), key=lambda j: -dets[j].score)
    trunk_only = [j for j in by_score if dets[j].class_id == CLASS_TRUNK]
    as_trunk = _greedy(iou, trunk_only, threshold)
    as_any = _greedy(iou, [j for j in by_score if dets[j].class_id in (CLASS_TRUNK, CLASS_POST)], threshold)
    return FrameMatch(len(gt), len(as_trunk), len(as_any), len(trunk_only) - len(as_trunk))


def centre_detection(dets: Sequence[Detection], width: int, height: int, classes: Sequence[int]) -> Detection | None:
    """Caliper sources: the detection (of `classes`) nearest the image's centre column whose mask is centred
    within CENTRE_BAND x width of it and at least MIN_HEIGHT x height tall; None if none."""
    best, best_d = None, CENTRE_BAND * width
    for d in dets:
        if d.class_id not in classes:
            continue
        v, u = np.nonzero(d.mask)
        if not len(u) or (v.max() - v.min() + 1) < MIN_HEIGHT * height:
            continue
        dist = abs(float(u.mean()) - width / 2.0)
        if dist <= best_d:
            best, best_d = d, dist
    return best


def mask_diameter_mm(mask: np.ndarray, depth_m: np.ndarray, fx: float) -> float | None:
    """Diameter of a trunk mask: the median width (px) of its middle 60 % rows x the median valid depth (m) on
    the mask / fx, in mm; None without depth on the mask."""
    rows = np.flatnonzero(mask.any(axis=1))
    if len(rows) < 3:
        return None
    lo, hi = rows[0] + int(0.2 * len(rows)), rows[0] + int(0.8 * len(rows))
    widths = mask[lo:hi + 1].sum(axis=1)
    widths = widths[widths > 0]
    z = depth_m[mask]
    z = z[np.isfinite(z) & (z > 0)]
    if not len(widths) or not len(z):
        return None
    return float(np.median(widths) * np.median(z) / fx * 1000.0)


def _load_source(folder: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The source's instances.json and, per image, its annotations (decoded masks or boxes) and extras."""
    from pycocotools import mask as mask_util

    doc = json.loads((folder / "instances.json").read_text())
    names = {int(c["id"]): str(c["name"]).lower() for c in doc["categories"]}
    by_image: dict[int, list[dict]] = {}
    for a in doc["annotations"]:
        by_image.setdefault(int(a["image_id"]), []).append(a)
    frames = []
    for im in doc["images"]:
        h, w = int(im["height"]), int(im["width"])
        trunks = []
        for a in by_image.get(int(im["id"]), []):
            if names.get(int(a["category_id"])) != "trunk" or a.get("iscrowd", 0):
                continue
            seg = a.get("segmentation")
            if doc["info"].get("annotation") == "box" or not seg:
                x, y, bw, bh = a["bbox"]
                trunks.append(np.array([x, y, x + bw, y + bh], float))
                continue
            if isinstance(seg, list):
                rle = mask_util.merge(mask_util.frPyObjects(seg, h, w))
            else:
                rle = dict(seg)
                if isinstance(rle["counts"], list):
                    rle = mask_util.frPyObjects(rle, h, w)
                elif isinstance(rle["counts"], str):
                    rle["counts"] = rle["counts"].encode("ascii")
            trunks.append(mask_util.decode(rle).astype(bool))
        frames.append({**im, "trunks": trunks})
    return doc["info"], frames


def _depth_m(folder: Path, im: dict[str, Any]) -> np.ndarray | None:
    if not im.get("depth_file"):
        return None
    raw = cv2.imread(str(folder / im["depth_file"]), cv2.IMREAD_UNCHANGED)
    if raw is None:
        return None
    scale = {"mm": 0.001, "cm": 0.01, "m": 1.0}[im.get("depth_unit", "mm")]
    z = raw.astype(np.float32) * scale
    z[raw == 0] = np.nan
    if z.shape != (im["height"], im["width"]):
        z = cv2.resize(z, (im["width"], im["height"]), interpolation=cv2.INTER_NEAREST)
    return z


def evaluate_source(folder: Path, detector: OnnxTrunkDetector) -> dict[str, Any]:
    info, frames = _load_source(folder)
    kind = info.get("annotation", "mask")
    totals = dict(frames=0, true_trunks=0, found_trunk=0, found_any=0, false_trunks=0)
    times, per_frame, diam_trunk, diam_any = [], [], [], []
    for im in frames:
        rgb = cv2.cvtColor(cv2.imread(str(folder / im["file_name"]), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        t0 = time.perf_counter()
        dets = detector.detect(rgb, where=im["file_name"])
        times.append(time.perf_counter() - t0)
        rec: dict[str, Any] = {"file": im["file_name"], "detections": len(dets),
                               "trunk_detections": sum(d.class_id == CLASS_TRUNK for d in dets)}
        if kind == "caliper":
            H, W = rgb.shape[:2]
            as_trunk = centre_detection(dets, W, H, (CLASS_TRUNK,))
            as_any = centre_detection(dets, W, H, (CLASS_TRUNK, CLASS_POST))
            m = FrameMatch(1, int(as_trunk is not None), int(as_any is not None), 0)
            z = _depth_m(folder, im)
            cal = im.get("caliper_diameter_mm")
            rec["caliper_mm"] = cal
            if z is not None and cal:
                for key, d, acc in (("diameter_trunk_mm", as_trunk, diam_trunk), ("diameter_any_mm", as_any, diam_any)):
                    est = mask_diameter_mm(d.mask, z, float(im["fx"])) if d is not None else None
                    rec[key] = est
                    if est is not None:
                        acc.append(est - cal)
        else:
            m = match_frame(im["trunks"], dets, "box" if kind == "box" else "mask")
        rec.update(asdict(m))
        per_frame.append(rec)
        totals["frames"] += 1
        for k in ("true_trunks", "found_trunk", "found_any", "false_trunks"):
            totals[k] += getattr(m, k)
    out: dict[str, Any] = {"source": folder.name, "origin": info.get("source"), "commit": info.get("commit"),
                           "annotation": kind, **totals,
                           "recall_trunk": totals["found_trunk"] / max(totals["true_trunks"], 1),
                           "recall_any": totals["found_any"] / max(totals["true_trunks"], 1),
                           "false_trunks_per_frame": (None if kind == "caliper"
                                                      else totals["false_trunks"] / max(totals["frames"], 1)),
                           "detections_per_frame": float(np.mean([r["detections"] for r in per_frame])),
                           "ms_per_frame": float(np.median(times)) * 1000 if times else None}
    for key, errs in (("diameter_trunk", diam_trunk), ("diameter_any", diam_any)):
        if errs:
            e = np.asarray(errs)
            out[key] = {"n": int(len(e)), "mae_mm": float(np.abs(e).mean()), "bias_mm": float(e.mean()),
                        "median_abs_mm": float(np.median(np.abs(e)))}
    out["frames_detail"] = per_frame
    return out


def _table(results: list[dict[str, Any]], title: str) -> None:
    from rich.console import Console
    from rich.table import Table

    t = Table(title=title)
    for c in ("source", "kind", "frames", "true trunks", "found trunk", "found trunk|post", "false trunks/frame",
              "detections/frame", "ms/frame", "diam MAE / bias mm (n)"):
        t.add_column(c, justify="left" if c in ("source", "kind") else "right")
    for r in results:
        d = r.get("diameter_any")
        diam = f"{d['mae_mm']:.1f} / {d['bias_mm']:+.1f} ({d['n']})" if d else "n/a"
        fpf = "n/a" if r["false_trunks_per_frame"] is None else f"{r['false_trunks_per_frame']:.2f}"
        t.add_row(r["source"], r["annotation"], str(r["frames"]), str(r["true_trunks"]),
                  f"{r['found_trunk']} ({100 * r['recall_trunk']:.1f} %)",
                  f"{r['found_any']} ({100 * r['recall_any']:.1f} %)", fpf, f"{r['detections_per_frame']:.2f}",
                  f"{r['ms_per_frame']:.0f}", diam)
    Console(width=200).print(t)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(DATA), help="folder of sources (one sub-folder with instances.json each)")
    ap.add_argument("--sources", nargs="*", help="only these sources (folder names)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="configuration override, e.g. trunks.flip_test=true (repeatable)")
    ap.add_argument("--json", help="write the results here")
    a = ap.parse_args(argv)
    cfg = load_config(None, unflatten(parse_sets(a.set)) if a.set else None)
    detector = OnnxTrunkDetector.from_params(cfg.trunks)
    folders = sorted(p for p in Path(a.data).iterdir() if (p / "instances.json").is_file())
    if a.sources:
        folders = [p for p in folders if p.name in a.sources]
    if not folders:
        print(f"no source under {a.data}", file=sys.stderr)
        return 2
    results = [evaluate_source(f, detector) for f in folders]
    _table(results, f"shipped detector on real photos ({', '.join(a.set) or 'default config'})")
    for r in results:
        for key in ("diameter_trunk", "diameter_any"):
            if key in r:
                d = r[key]
                print(f"{r['source']} {key}: n {d['n']}, MAE {d['mae_mm']:.1f} mm, bias {d['bias_mm']:+.1f} mm, "
                      f"median |error| {d['median_abs_mm']:.1f} mm")
    if a.json:
        doc = {"date": datetime.date.today().isoformat(), "model": str(detector.path), "sets": a.set,
               "trunks": {k: v for k, v in cfg.trunks.__dict__.items() if not k.startswith("_")}
               if hasattr(cfg.trunks, "__dict__") else None,
               "iou_threshold": IOU_THRESHOLD, "centre_band": CENTRE_BAND, "min_height": MIN_HEIGHT,
               "sources": results}
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(portable_json(doc, indent=1, default=str))
        print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
