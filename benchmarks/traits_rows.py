"""Tree height and canopy volume on simulated rows, against the simulator's truth, method by method.

    .venv/bin/python benchmarks/traits_rows.py [--rows standard:31 wind:32 slope_weeds:33] [--trees 10]
        [--workdir DIR (default: the system temporary folder/traits_rows)] [--reuse] [--json out.json]
        [--set KEY=VALUE ...]  (the merge and traits stage's configuration, e.g. --set traits.share_reach_m=0)

Per row: simulate (seeded), reconstruct both sides once (pipeline.reconstruct_side), then the merge and the
traits stage with each segmentation (cutting planes, shrink-and-expand) and the practice the paper replaces
(one side's crown, its volume doubled; its height as it is), scored per tree against ground_truth.json
(height MAE cm, canopy volume MAPE and bias %, the share of points on a tree's surface given to that tree,
overall and where crowns touch: eval.segmentation) with the traits stage's seconds. One table, one row per
(row, method).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

from orchard_mapping.config import load_config, parse_sets, unflatten
from orchard_mapping.eval.evaluate import evaluate_result
from orchard_mapping.io.results import portable_json, write_trees
from orchard_mapping.io.sidemap_codec import decode_side_map, encode_side_map
from orchard_mapping.pipeline.merge import merge_to_trees
from orchard_mapping.pipeline.outputs import write_tree_cloud
from orchard_mapping.pipeline.side import reconstruct_side
from orchard_mapping.pipeline.sides import Timings, open_sides
from orchard_mapping.pipeline.traits import measure_trees
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import simulate


def side_maps(row: Path, scenario: str, seed: int, trees: int, reuse: bool,
              sim_sets: dict | None = None) -> tuple[Path, dict]:
    """The row simulated (scenario, seed, trees, the scenario overrides sim_sets) and each side reconstructed,
    in `row`; with reuse, what is there already is read back."""
    sim = row / "sim"
    if not (reuse and (sim / "ground_truth.json").is_file()):
        simulate(load_scenario(scenario, {"row.n_trees": trees, **(sim_sets or {})}), seed, sim)
    cfg = load_config()
    maps = {}
    for side, seq in open_sides(sim / "front", sim / "back", cfg).items():
        path = row / f"{side}.sidemap"
        if not (reuse and path.is_file()):
            path.write_bytes(encode_side_map(reconstruct_side(seq, side, cfg, Timings())))
        maps[side] = decode_side_map(path.read_bytes())
    return sim, maps


def _score(truth: Path, trees: list, labels) -> dict:
    """The evaluator's trait errors and per-point segmentation score of these trees against the truth (trees.json
    and trees.laz in a scratch folder)."""
    with tempfile.TemporaryDirectory() as d:
        write_trees(d, trees, frame="map")
        write_tree_cloud(Path(d), labels)
        rep = evaluate_result(truth, d).to_dict()
    t, sg = rep["traits"], rep["segmentation"] or {}
    return {"matched": rep["matching"]["matched"], "height_mae_cm": t["height_mae_cm"],
            "volume_mape_pct": t["canopy_volume_mape_percent"], "volume_bias_pct": t["canopy_volume_bias_percent"],
            "seg_accuracy_pct": None if sg.get("accuracy") is None else 100 * sg["accuracy"],
            "seg_touching_pct": None if sg.get("accuracy_near_neighbour") is None
            else 100 * sg["accuracy_near_neighbour"],
            "interval_coverage": {k: v["coverage"] for k, v in (t.get("interval_coverage") or {}).items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", nargs="+", default=["standard:31", "wind:32", "slope_weeds:33"],
                    help="scenario:seed per row")
    ap.add_argument("--trees", type=int, default=10)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "traits_rows")
    ap.add_argument("--reuse", action="store_true", help="reuse simulated rows and side maps in --workdir")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="configuration of the merge and the traits stage (repeatable)")
    a = ap.parse_args()
    rows = []
    print("| row | method | trees | height MAE cm | volume MAPE % | volume bias % | points right % "
          "| where crowns touch % | traits s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for spec in a.rows:
        scenario, seed = spec.split(":")
        sim, maps = side_maps(a.workdir / f"{scenario}_{seed}_{a.trees}trees", scenario, int(seed), a.trees, a.reuse)
        cfg = load_config(overrides=unflatten(parse_sets(a.set)))
        merged, clouds, trees = merge_to_trees(maps, cfg)
        for method in ("cutting_planes", "shrink_and_expand", "one_side_doubled"):
            c = cfg.model_copy(update={"traits": dataclasses.replace(
                cfg.traits, segmentation="cutting_planes" if method == "one_side_doubled" else method)})
            use_maps, use_clouds = maps, clouds
            if method == "one_side_doubled":  # the front side's crown alone, as practice measures it
                back = maps["back"]
                use_maps = {**maps, "back": dataclasses.replace(back, cloud_points=back.cloud_points[:0],
                                                                 cloud_colors=back.cloud_colors[:0])}
                use_clouds = {**clouds, "back": clouds["back"][:0]}
            t0 = time.perf_counter()
            measured, labels = measure_trees(merged, use_maps, use_clouds, trees, c)
            secs = time.perf_counter() - t0
            if method == "one_side_doubled":
                measured = [dataclasses.replace(t, canopy_volume_m3=2 * t.canopy_volume_m3)
                            if t.canopy_volume_m3 is not None else t for t in measured]
            s = _score(sim / "ground_truth.json", measured, labels)
            rows.append({"row": spec, "method": method, "seconds": secs, **s})
            fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
            print(f"| {spec} | {method} | {s['matched']} | {fmt(s['height_mae_cm'])} | {fmt(s['volume_mape_pct'])} "
                  f"| {fmt(s['volume_bias_pct'])} | {fmt(s['seg_accuracy_pct'])} | {fmt(s['seg_touching_pct'])} "
                  f"| {secs:.2f} |", flush=True)
    if a.json:
        a.json.write_text(portable_json({"benchmark": "traits_rows", "trees": a.trees, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
