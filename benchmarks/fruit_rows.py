"""Fruit counts on simulated rows against the simulator's truth, with the baselines the paper compares.

    .venv/bin/python benchmarks/fruit_rows.py [--rows standard:51] [--sources masks model] [--trees 10]
        [--workdir DIR (default: the system temporary folder/traits_rows)] [--json out.json]
        [--sim-set fruit.red_fraction=0 ...]  (scenario overrides of every row: a colour mix)
        [--set fruit.model=FILE ...]  (configuration overrides of the product)

Per row it reuses (or makes, as benchmarks/traits_rows.py does) each side's reconstruction, then runs the fruit
stage on the side's keyframes (pipeline.fruit.FruitTap over the bag's keyframe images, with the side map's
optimised poses) with each fruit source: `masks` (the simulator's own fruit masks: the 3D stage alone) and
`model` (the pixel model: the whole stage). Then the merge and the traits stage, and for the row:

- front only, back only, the naive sum of both sides, the paper's inclusion-exclusion, and the product's
  association (each fruit once): counts against the fruit visible from either side and all fruit;
- the evaluator's duplicates per fruit seen from both sides, fruit position error and diameter MAE;
- the per-tree count error (median |est - visible| / visible) and the fruit stage's seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path

import numpy as np
import yaml

from orchard_mapping.config import load_config, parse_sets, unflatten
from orchard_mapping.core.fruit import inclusion_exclusion_count
from orchard_mapping.eval.evaluate import evaluate_result
from orchard_mapping.eval.ground_truth import load_ground_truth
from orchard_mapping.io.results import portable_json, write_trees
from orchard_mapping.pipeline.fruit import add_fruit, side_fruit_in_map
from orchard_mapping.pipeline.merge import map_poses, merge_to_trees
from orchard_mapping.pipeline.sides import open_sides
from orchard_mapping.pipeline.traits import measure_trees
from traits_rows import side_maps  # benchmarks/ is the script's folder


def _with_fruit(sim: Path, maps: dict, cfg) -> tuple[dict, float]:
    """The side maps with their fruit, found on the keyframes of each side's bag (segmentation and placing;
    the bag's decoding included); the stage's seconds."""
    seqs = open_sides(sim / "front", sim / "back", cfg)
    out, secs = {}, 0.0
    for side, sm in maps.items():
        out[side], s = add_fruit(sm, seqs[side], cfg.fruit)
        secs += s
    return out, secs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", nargs="+", default=["standard:51"], help="scenario:seed per row")
    ap.add_argument("--sources", nargs="+", default=["masks", "model"], choices=["masks", "model"])
    ap.add_argument("--trees", type=int, default=10)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "traits_rows")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--sim-set", action="append", default=[], metavar="KEY=VALUE",
                    help="scenario override for every row, e.g. fruit.red_fraction=0 (green fruit only)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="configuration override, e.g. fruit.model=my_model.onnx")
    a = ap.parse_args()
    rows = []
    print("| row | source | visible / all | front | back | naive sum | incl.-excl. | ours | ours vs visible % "
          "| per-tree error % (median) | twice % of both | position mm | diameter MAE / bias mm | fruit s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for spec in a.rows:
        scenario, seed = spec.split(":")
        sim_sets = dict(kv.split("=", 1) for kv in a.sim_set)
        tag = "".join(f"_{k.split('.')[-1]}{v}" for k, v in sim_sets.items())  # e.g. _red_fraction0.0
        sim, maps = side_maps(a.workdir / f"{scenario}_{seed}_{a.trees}trees{tag}", scenario, int(seed), a.trees,
                              True, {k: yaml.safe_load(v) for k, v in sim_sets.items()})
        gt = load_ground_truth(sim / "ground_truth.json")
        visible = sum(t.fruit_visible["either"] for t in gt.trees)
        total = sum(t.fruit_count for t in gt.trees)
        for source in a.sources:
            base = load_config(None, unflatten(parse_sets(a.set)) if a.set else None)
            cfg = base.model_copy(update={"fruit": dataclasses.replace(
                base.fruit, enabled=True, source=source, masks_dir=str(sim / "masks"))})
            fmaps, secs = _with_fruit(sim, maps, cfg)
            merged, clouds, trees = merge_to_trees(fmaps, cfg)
            measured, _ = measure_trees(merged, fmaps, clouds, trees, cfg)
            poses = map_poses(merged, fmaps)
            moved = {s: side_fruit_in_map(fmaps[s], poses[s]) for s in fmaps}
            counts = {"front": len(fmaps["front"].fruit.positions), "back": len(fmaps["back"].fruit.positions)}
            counts["naive"] = counts["front"] + counts["back"]
            counts["ie"] = inclusion_exclusion_count(moved["front"], moved["back"], cfg.fruit)
            counts["ours"] = sum(t.fruit_count or 0 for t in measured) + sum(
                t.extra.get("fruit_on_ground", 0) for t in measured)
            with tempfile.TemporaryDirectory() as d:
                write_trees(d, measured, frame="map")
                rep = evaluate_result(sim / "ground_truth.json", d).to_dict()
            dc = rep["double_count"] or {}
            per_tree = [abs(p["est_fruit_count"] - p["true_fruit_visible"]) / p["true_fruit_visible"]
                        for p in rep["per_tree"] if p["est_fruit_count"] is not None and p["true_fruit_visible"]]
            row = {"row": spec, "source": source, "visible": visible, "all": total, **counts,
                   "ours_vs_visible_pct": 100.0 * (counts["ours"] - visible) / visible if visible else None,
                   "per_tree_error_median_pct": 100.0 * float(np.median(per_tree)) if per_tree else None,
                   "twice_per_both_pct": dc.get("per_both_percent"),
                   "position_error_median_mm": dc.get("position_error_median_mm"),
                   "diameter_mae_mm": dc.get("diameter_mae_mm"), "diameter_bias_mm": dc.get("diameter_bias_mm"),
                   "fruit_seconds": secs}
            rows.append(row)
            f = lambda v, d=1: "n/a" if v is None else f"{v:.{d}f}"  # noqa: E731
            print(f"| {spec} | {source} | {visible} / {total} | {counts['front']} | {counts['back']} | "
                  f"{counts['naive']} | {counts['ie']} | {counts['ours']} | {f(row['ours_vs_visible_pct'])} | "
                  f"{f(row['per_tree_error_median_pct'])} | {f(row['twice_per_both_pct'])} | "
                  f"{f(row['position_error_median_mm'])} | {f(row['diameter_mae_mm'])} / {f(row['diameter_bias_mm'])} | {secs:.1f} |", flush=True)
    if a.json:
        a.json.write_text(portable_json({"benchmark": "fruit_rows", "trees": a.trees, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
