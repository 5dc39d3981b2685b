"""Benchmark: a whole block in one drive (docs/usage.md, "A whole block in one drive").

For each seed: simulate the `block` scenario (3 rows of 2 trees by default, one bag, 10 Hz), run `orchard-map
run`'s pipeline on the one bag (the rows and sides from the camera's turns, each row merged and measured into
row_<k>/, block.csv), then score each row against its truth (eval.block). Prints one line per row: the passes
(frames), trees found of the true ones and false ones, the largest two-side trunk diameter error and the
diameter MAE, each side's drift, the merge's error, and the times; --json writes it all.

Trunks from the simulator's true masks by default (as the tests of a drive round one row); --detector: from
the shipped detector and the geometry, the default configuration.

Usage:
  python benchmarks/block_drive.py [--rows 3] [--trees 2] [--rate 10] [--seeds 0 1 2] [--workdir /tmp/block_bench]
        [--reuse] [--detector] [--sim-set path.speed_mps=0.7] [--json benchmarks/results/block_drive.json]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from orchard_mapping.config import load_config, parse_sets  # noqa: E402
from orchard_mapping.errors import MergeRefusedError  # noqa: E402
from orchard_mapping.eval.block import evaluate_block  # noqa: E402
from orchard_mapping.io.block import read_block  # noqa: E402
from orchard_mapping.io.results import portable_json  # noqa: E402
from orchard_mapping.pipeline import run  # noqa: E402
from orchard_mapping.sim.scenario import load_scenario  # noqa: E402
from orchard_mapping.sim.simulate import simulate  # noqa: E402


def one_block(seed: int, args: argparse.Namespace, workdir: Path) -> dict[str, Any]:
    sim = workdir / f"sim_s{seed}"
    overrides = {"block.rows": args.rows, "row.n_trees": args.trees, "camera.rate_hz": args.rate,
                 "masks_every": 0 if args.detector else 1, **parse_sets(args.sim_set)}
    t0 = time.perf_counter()
    if not (args.reuse and (sim / "ground_truth.json").is_file()):
        simulate(load_scenario("block", overrides), seed, sim, force=True, compress=True)
    sim_s = time.perf_counter() - t0
    out = workdir / f"result_s{seed}"
    trunks = {} if args.detector else {"trunks": {"source": "masks", "masks_dir": str(sim / "masks" / "block")}}
    cfg = load_config(overrides=trunks)
    t0 = time.perf_counter()
    refused = None
    try:
        run(sim / "block", None, out, cfg, trunk_worker=True)
    except MergeRefusedError as err:  # the rows are written all the same
        refused = str(err)
    run_s = time.perf_counter() - t0
    ev = evaluate_block(sim / "ground_truth.json", out)
    rows = []
    summary = {r.row: r for r in read_block(out / "block.json")}
    for r in ev.rows:
        s = summary.get(r.row)
        row: dict[str, Any] = {"row": r.row, "status": s.status if s else "absent", "true_trees": r.true_trees,
                               "passes": {p.side: p.frames for p in s.passes} if s else {}}
        rep = r.report
        if rep is not None and rep.matching is not None:
            errs = [1000 * (p.est_trunk_diameter_m - p.true_trunk_diameter_m) for p in rep.pairs
                    if p.est_trunk_diameter_m is not None]
            row.update(matched=rep.matching.matched, false=rep.matching.false,
                       diameter_errors_mm=[round(e, 2) for e in errs],
                       diameter_mae_mm=rep.traits.trunk_diameter_mae_mm if rep.traits else None,
                       drift_percent={k: (v.drift_percent if v else None) for k, v in rep.sides.items()},
                       merge_deg=rep.merge.rotation_error_deg if rep.merge else None,
                       merge_mm=rep.merge.translation_error_mm if rep.merge else None)
        rows.append(row)
    return {"seed": seed, "frames": sum(sum(r["passes"].values()) for r in rows), "simulate_s": round(sim_s, 1),
            "run_s": round(run_s, 1), "refused": refused, "rows": rows}


def table(results: list[dict[str, Any]]) -> Table:
    t = Table(title="a whole block in one drive")
    for col in ("seed", "row", "passes (frames)", "trees", "false", "diameter errors mm", "MAE mm",
                "drift % front / back", "merge deg / mm", "sim s / run s"):
        t.add_column(col, justify="right")
    for res in results:
        for k, r in enumerate(res["rows"]):
            d = r.get("drift_percent") or {}

            def f(v: float | None, fmt: str = ".2f") -> str:
                return "n/a" if v is None else format(v, fmt)

            t.add_row(str(res["seed"]) if k == 0 else "", str(r["row"]),
                      " / ".join(f"{side} {n}" for side, n in r["passes"].items()),
                      f"{r.get('matched', '-')}/{r['true_trees']}" + ("" if r["status"] == "measured" else f" {r['status']}"),
                      str(r.get("false", "")), " ".join(f"{e:+.1f}" for e in r.get("diameter_errors_mm", [])),
                      f(r.get("diameter_mae_mm")), f"{f(d.get('front'))} / {f(d.get('back'))}",
                      f"{f(r.get('merge_deg'), '.3f')} / {f(r.get('merge_mm'), '.1f')}",
                      f"{res['simulate_s']:.0f} / {res['run_s']:.0f}" if k == 0 else "")
    return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=3)
    ap.add_argument("--trees", type=int, default=2, help="trees per row")
    ap.add_argument("--rate", type=float, default=10.0, help="Hz")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "block_bench")
    ap.add_argument("--reuse", action="store_true", help="reuse the simulated blocks already in --workdir")
    ap.add_argument("--detector", action="store_true", help="trunks from the shipped detector, not the true masks")
    ap.add_argument("--sim-set", action="append", default=[], help="scenario override, e.g. path.speed_mps=0.7")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    results = [one_block(seed, args, args.workdir) for seed in args.seeds]
    Console(width=160).print(table(results))
    if args.json:
        args.json.write_text(portable_json({"args": {k: str(v) if isinstance(v, Path) else v
                                                     for k, v in vars(args).items() if k != "json"},
                                            "results": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
