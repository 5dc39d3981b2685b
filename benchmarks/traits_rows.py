"""Tree height and canopy volume on simulated rows, against the simulator's truth, method by method.

    .venv/bin/python benchmarks/traits_rows.py [--rows standard:31 wind:32 slope_weeds:33] [--trees 10]
        [--workdir DIR (default: the system temporary folder/traits_rows)] [--reuse] [--json out.json]

Per row: simulate (seeded), reconstruct both sides once (pipeline.reconstruct_side), then the merge and the
traits stage with each segmentation (cutting planes, shrink-and-expand) and the practice the paper replaces
(one side's crown, its volume doubled; its height as it is), scored per tree against ground_truth.json
(height MAE cm, canopy volume MAPE and bias %) with the traits stage's seconds. One table, one row per
(row, method).
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from orchard_mapping.config import load_config
from orchard_mapping.core.geometry import transform_points
from orchard_mapping.eval.ground_truth import load_ground_truth
from orchard_mapping.eval.metrics import match_trees
from orchard_mapping.io.results import portable_json
from orchard_mapping.io.sidemap_codec import decode_side_map, encode_side_map
from orchard_mapping.pipeline.merge import merge_to_trees
from orchard_mapping.pipeline.side import reconstruct_side
from orchard_mapping.pipeline.sides import Timings, open_sides
from orchard_mapping.pipeline.traits import measure_trees
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import simulate


def _sides(row: Path, scenario: str, seed: int, trees: int, reuse: bool) -> tuple[Path, dict]:
    sim = row / "sim"
    if not (reuse and (sim / "ground_truth.json").is_file()):
        simulate(load_scenario(scenario, {"row.n_trees": trees}), seed, sim)
    cfg = load_config()
    maps = {}
    for side, seq in open_sides(sim / "front", sim / "back", cfg).items():
        path = row / f"{side}.sidemap"
        if not (reuse and path.is_file()):
            path.write_bytes(encode_side_map(reconstruct_side(seq, side, cfg, Timings())))
        maps[side] = decode_side_map(path.read_bytes())
    return sim, maps


def _score(gt, trees: list, radius_m: float) -> dict:
    """Height MAE (cm), volume MAPE and bias (%) of the trees matched to the truth (as orchard-map evaluate)."""
    true_xyz = transform_points(np.linalg.inv(gt.sides["front"].T_world_odom),
                                np.array([t.position for t in gt.trees]).reshape(-1, 3))  # world -> map
    m = match_trees(true_xyz, np.array([t.position for t in trees]).reshape(-1, 3), radius_m)
    dh, dv = [], []
    for i, j in zip(m.true_index.tolist(), m.est_index.tolist(), strict=True):
        t, e = gt.trees[i], trees[j]
        if e.height_m is not None:
            dh.append(100 * (e.height_m - t.height_m))
        if e.canopy_volume_m3 is not None and t.canopy_volume_m3:
            dv.append(100 * (e.canopy_volume_m3 - t.canopy_volume_m3) / t.canopy_volume_m3)
    return {"matched": len(m.true_index), "height_mae_cm": float(np.mean(np.abs(dh))) if dh else None,
            "volume_mape_pct": float(np.mean(np.abs(dv))) if dv else None,
            "volume_bias_pct": float(np.mean(dv)) if dv else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", nargs="+", default=["standard:31", "wind:32", "slope_weeds:33"],
                    help="scenario:seed per row")
    ap.add_argument("--trees", type=int, default=10)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "traits_rows")
    ap.add_argument("--reuse", action="store_true", help="reuse simulated rows and side maps in --workdir")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    rows = []
    print("| row | method | trees | height MAE cm | volume MAPE % | volume bias % | traits s |")
    print("|---|---|---|---|---|---|---|")
    for spec in a.rows:
        scenario, seed = spec.split(":")
        sim, maps = _sides(a.workdir / f"{scenario}_{seed}_{a.trees}trees", scenario, int(seed), a.trees, a.reuse)
        gt = load_ground_truth(sim / "ground_truth.json")
        cfg = load_config()
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
            measured, _ = measure_trees(merged, use_maps, use_clouds, trees, c)
            secs = time.perf_counter() - t0
            if method == "one_side_doubled":
                measured = [dataclasses.replace(t, canopy_volume_m3=2 * t.canopy_volume_m3)
                            if t.canopy_volume_m3 is not None else t for t in measured]
            s = _score(gt, measured, cfg.evaluate.match_radius_m)
            rows.append({"row": spec, "method": method, "seconds": secs, **s})
            fmt = lambda v: "n/a" if v is None else f"{v:.2f}"  # noqa: E731
            print(f"| {spec} | {method} | {s['matched']} | {fmt(s['height_mae_cm'])} | {fmt(s['volume_mape_pct'])} "
                  f"| {fmt(s['volume_bias_pct'])} | {secs:.2f} |", flush=True)
    if a.json:
        a.json.write_text(portable_json({"benchmark": "traits_rows", "trees": a.trees, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
