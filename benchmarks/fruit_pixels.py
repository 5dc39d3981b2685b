"""Benchmark: fruit pixels and fruit instances (orchard_mapping.core.fruit_pixels) on held-out simulated frames,
and on real photographs where a folder of them is given.

Simulated: the held-out seeds of orchard_mapping.train.fruit_pixels (HELDOUT_SEEDS, never used for training or
for a choice), 2-tree rows, `--frames` frames per side spread over both sweeps, in each colour mix (red_fraction
1.0, 0.0, 0.6) and three looks: `standard` (the standard scenario's colours and light), `randomised` (each scene
drawn by sim.domain.random_domain: sun, shade, leaf, soil, hedge and sky colours, blur, noise) and `varied` (the
randomised look with the varied fruit, `fruit.look: varied`: blush, streaks, golden and pink varieties). Per
approach (the colour GMM and the small network of models/, or the files given with --model), one row:

  pixel P/R/F1   over all pixels of the mix's frames
  inst R         true fruit (>= 20 visible px, the simulator's visibility rule) matched by a predicted instance
                 with mask IoU >= 0.5
  inst R 50%     the same over the fruit with at least half of their projected disc visible in the frame
  inst P         predicted instances matched so, over the predicted instances (those matching an uncounted
                 fruit left out)
  cc R           inst R with one instance per connected component (no splitting of touching fruit)
  ms             median time of segment_fruit per 640 x 480 frame (scores, mask, instances)

A row `truth` splits the true fruit mask itself: the ceiling that instance splitting reaches with perfect pixels.

Real (`--real DIR`: a folder with images/*.jpg and YOLO labels/*.txt, class x y w h normalised; see
docs/fruit.md for the one measured). Only boxes are annotated there, so: box recall (a true box matched by a
predicted instance's bounding box with IoU >= 0.5), instance precision likewise, and the share of predicted fruit
pixels inside any true box (an upper bound of pixel precision). Never tuned on. `--real-scales`: the photographs
resized by each factor first (a photograph's fruit may be several times the pixels the simulator's camera gives
a fruit at 1.4 m: 30-45 px); each scale is reported, none chosen.

Second renderer (`--splat-rows N`, an unseen domain like the real photographs: never trained or tuned on): N rows
of real scanned trees with fruit (sim/scan_rows.py: the point-splatting renderer and stereo-like camera, its own
fruit look; seeds 2000.., 4 trees, 20-40 fruit each), `--frames` x 2 frames per side spread over the steady
path; the same scores as the simulated rows (look `splat`), fruit mix 0.6 red.

Usage:
  python benchmarks/fruit_pixels.py [--frames 4] [--looks standard randomised varied] [--real DIR]
        [--real-scales 1 0.5 0.25] [--splat-rows 2] [--model NAME=FILE ...] [--json benchmarks/results/fruit_pixels.json]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from orchard_mapping.core import fruit_pixels as fp
from orchard_mapping.io.results import portable_json
from orchard_mapping.train import fruit_pixels as tf

ROOT = Path(__file__).resolve().parents[1]
MODELS = {"gmm": ROOT / "models" / "fruit_colour_gmm.json", "net": ROOT / "models" / "fruit_net.onnx"}
MIXES = {"red": 1.0, "green": 0.0, "mixed": 0.6}


def _sums(scores: list[fp.FrameScore]) -> dict[str, float]:
    tp, fpos, fn = (sum(getattr(s, k) for s in scores) for k in ("true_positive", "false_positive", "false_negative"))
    p, r = tp / max(tp + fpos, 1), tp / max(tp + fn, 1)
    true_n, found = sum(s.true_instances for s in scores), sum(s.found for s in scores)
    pred_n, matched = sum(s.predicted for s in scores), sum(s.matched_predictions for s in scores)
    return {"precision": round(p, 4), "recall": round(r, 4), "f1": round(2 * p * r / max(p + r, 1e-9), 4),
            "instance_recall": round(found / max(true_n, 1), 4), "instance_precision": round(matched / max(pred_n, 1), 4),
            "true_instances": true_n, "frames": len(scores)}


def _score(f: tf.LabelledFrame, pred: fp.FruitMask) -> tuple[fp.FrameScore, fp.FrameScore, fp.FrameScore]:
    """(all fruit >= 20 px, fruit >= 50 % visible, components only) scores of pred on frame f."""
    inst, n = fp.split_instances(pred.mask, fp.FruitMaskParams(split="none"))
    return (fp.score_frame(pred, f.instances), fp.score_frame(pred, f.instances, counted=f.visible_fraction >= 0.5),
            fp.score_frame(fp.FruitMask(pred.mask, inst, n), f.instances))


def splat_frames(seed: int, frames_per_side: int) -> list[tf.LabelledFrame]:
    """Frames of one scan row with fruit from the second renderer, labelled like the simulator's."""
    from orchard_mapping.core.types import CameraIntrinsics
    from orchard_mapping.sim.scan_row_scene import ScanRowSpec, build_scan_row
    from orchard_mapping.sim.scenario import load_scenario
    from orchard_mapping.sim.splat import PCls, SplatRenderer, StereoSensor
    from orchard_mapping.sim.trajectory import side_path

    spec = ScanRowSpec(n_trees=4, fruit_per_tree=(20, 40))
    row = build_scan_row(seed, spec)
    K = CameraIntrinsics(spec.width, spec.height, spec.fx, spec.fy, spec.cx, spec.cy)
    sc = load_scenario(spec.motion, {"camera.rate_hz": spec.rate_hz, "row.margin_m": spec.margin_m})
    renderer = SplatRenderer(row.points, K)
    centres = np.array([f.position for f in row.fruit]).reshape(-1, 3)
    radii = np.array([f.radius for f in row.fruit])
    out = []
    for k, side in enumerate(("front", "back")):
        rng = np.random.default_rng([seed, 5, k])
        path = side_path(sc, side, row.row_x, row.ground, rng, 0.0)  # type: ignore[arg-type]
        sensor = StereoSensor(wb_gain=(rng.uniform(1.02, 1.1), 1.0, rng.uniform(0.82, 0.95)))
        n = len(path.poses)
        for i in np.unique(np.linspace(0, n - 1, 2 * frames_per_side + 2).round().astype(int)[1:-1]):
            f = renderer.render(path.poses[i])
            color, _ = sensor.apply(f, K.fx, rng)
            inst = np.where(f.cls == PCls.FRUIT, f.inst + 1, 0).astype(np.int32)
            Tcw = np.linalg.inv(path.poses[i])
            z = centres @ Tcw[2, :3] + Tcw[2, 3]
            disc = np.pi * (K.fx * radii / np.maximum(z, 1e-3)) ** 2
            seen = np.bincount(inst.ravel(), minlength=len(radii) + 1)[1:] / disc
            out.append(tf.LabelledFrame(color, inst, seed, int(i), side,
                                        np.concatenate([[0.0], np.where(z > 0, seen, 0.0)])))
    return out


def simulated(models: dict[str, fp.FruitPixelModel], looks: list[str], frames: int, splat_rows: int = 0
              ) -> list[dict[str, Any]]:
    rows = []
    runs: list[tuple[str, str, float]] = [(look, mix, rf) for look in looks for mix, rf in MIXES.items()]
    runs += [("splat", "mixed", 0.6)] if splat_rows else []
    for look, mix, rf in runs:
        if look == "splat":
            data = [f for s in range(2000, 2000 + splat_rows) for f in splat_frames(s, frames)]
        else:
            data = tf.frames_for(tf.HELDOUT_SEEDS, red_fraction=rf, randomise=look != "standard",
                                 frames_per_side=frames, fruit_look="varied" if look == "varied" else "plain")
        for name, model in {**models, "truth": None}.items():
            scores, half, cc, ms = [], [], [], []
            for f in data:
                t0 = time.perf_counter()
                if model is None:
                    inst, n = fp.split_instances(f.instances > 0)
                    pred = fp.FruitMask(inst > 0, inst, n)
                else:
                    pred = fp.segment_fruit(f.rgb, model)
                ms.append(1000 * (time.perf_counter() - t0))
                a, b, c = _score(f, pred)
                scores.append(a)
                half.append(b)
                cc.append(c)
            row = {"look": look, "mix": mix, "red_fraction": rf, "model": name, **_sums(scores),
                   "instance_recall_half_visible": _sums(half)["instance_recall"],
                   "half_visible_instances": _sums(half)["true_instances"],
                   "cc_instance_recall": _sums(cc)["instance_recall"], "ms": round(float(np.median(ms)), 1)}
            rows.append(row)
            print(f"{look:10s} {mix:6s} {name:5s} P {row['precision']:.3f} R {row['recall']:.3f} "
                  f"F1 {row['f1']:.3f} | inst R {row['instance_recall']:.3f} (50% {row['instance_recall_half_visible']:.3f}) "
                  f"P {row['instance_precision']:.3f} cc R {row['cc_instance_recall']:.3f} "
                  f"({row['true_instances']}/{row['half_visible_instances']} fruit) {row['ms']:.0f} ms", flush=True)
    return rows


def _boxes(inst: np.ndarray, n: int) -> np.ndarray:
    """(n, 4) x1 y1 x2 y2 (pixel borders) of instances 1..n."""
    out = np.zeros((n, 4))
    for k in range(1, n + 1):
        ys, xs = np.nonzero(inst == k)
        out[k - 1] = (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1) if len(xs) else 0
    return out


def _box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(A, B) IoU of boxes a (A, 4) and b (B, 4)."""
    lo = np.maximum(a[:, None, :2], b[None, :, :2])
    hi = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=2)
    area = lambda x: np.prod(x[:, 2:] - x[:, :2], axis=1)  # noqa: E731
    return inter / np.maximum(area(a)[:, None] + area(b)[None, :] - inter, 1e-9)


def real(models: dict[str, fp.FruitPixelModel], folder: Path, scales: list[float]) -> list[dict[str, Any]]:
    images = sorted((folder / "images").glob("*.jpg"))
    rows = []
    for (name, model), scale in ((m, s) for m in models.items() for s in scales):
        true_n = found = pred_n = matched = 0
        in_box = px = 0
        ms = []
        for path in images:
            rgb = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)
            if scale != 1.0:
                rgb = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
            h, w = rgb.shape[:2]
            text = (folder / "labels" / f"{path.stem}.txt").read_text().split()
            lab = np.asarray(text, float).reshape(-1, 5)  # (B, 5) class x y w h; an empty file: no fruit
            gt = np.stack([(lab[:, 1] - lab[:, 3] / 2) * w, (lab[:, 2] - lab[:, 4] / 2) * h,
                           (lab[:, 1] + lab[:, 3] / 2) * w, (lab[:, 2] + lab[:, 4] / 2) * h], 1)
            t0 = time.perf_counter()
            pred = fp.segment_fruit(rgb, model)
            ms.append(1000 * (time.perf_counter() - t0))
            iou = _box_iou(gt, _boxes(pred.instances, pred.count))
            hit = iou >= 0.5
            true_n += len(gt)
            found += int(hit.any(1).sum())
            pred_n += pred.count
            matched += int(hit.any(0).sum())
            cover = np.zeros((h, w), bool)
            for x1, y1, x2, y2 in gt.round().astype(int):
                cover[max(y1, 0):y2, max(x1, 0):x2] = True
            in_box += int(np.count_nonzero(pred.mask & cover))
            px += int(np.count_nonzero(pred.mask))
        row = {"source": folder.name, "model": name, "scale": scale, "images": len(images), "true_boxes": true_n,
               "box_recall": round(found / max(true_n, 1), 4), "instance_precision": round(matched / max(pred_n, 1), 4),
               "predicted_per_image": round(pred_n / max(len(images), 1), 1),
               "fruit_pixels_in_boxes": round(in_box / max(px, 1), 4), "ms": round(float(np.median(ms)), 1)}
        rows.append(row)
        print(f"real {folder.name} x{scale:g} {name}: box recall {row['box_recall']:.3f} ({true_n} boxes, {len(images)} images), "
              f"instance precision {row['instance_precision']:.3f}, {row['predicted_per_image']} instances/image, "
              f"fruit pixels in boxes {row['fruit_pixels_in_boxes']:.3f}, {row['ms']:.0f} ms", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=4, help="frames per side and scene")
    ap.add_argument("--looks", nargs="*", default=["standard", "randomised", "varied"],
                    choices=["standard", "randomised", "varied"])
    ap.add_argument("--real-scales", nargs="+", type=float, default=[1.0])
    ap.add_argument("--splat-rows", type=int, default=0, help="rows of the second renderer with fruit (0: none)")
    ap.add_argument("--model", action="append", default=[], metavar="NAME=FILE",
                    help="score these model files instead of the shipped two (repeat)")
    ap.add_argument("--real", type=Path, default=None, help="folder with images/*.jpg and YOLO labels/*.txt")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    files = dict(m.split("=", 1) for m in a.model) if a.model else MODELS
    models = {k: fp.load_model(p) for k, p in files.items()}
    rows = simulated(models, a.looks, a.frames, a.splat_rows)
    real_rows = real(models, a.real, a.real_scales) if a.real else []
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(portable_json({"benchmark": "fruit_pixels", "heldout_seeds": list(tf.HELDOUT_SEEDS),
                                         "frames_per_side": a.frames, "trees": 2, "simulated": rows,
                                         "real": real_rows, "params": repr(fp.FruitMaskParams())}, indent=1))


if __name__ == "__main__":
    main()
