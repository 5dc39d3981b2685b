"""Benchmark on an unseen domain: rows of real laser-scanned trees rendered by an independent renderer.

Never used for training or tuning. Each row is built by `orchard_mapping.sim.scan_rows.generate_scan_row`
(real TLS pines from benchmarks/data/real_trees scaled to 2.0-2.8 m, posts, wire, bumpy ground, neighbouring
rows; point-splatting renderer and stereo-like sensor of `sim/splat.py`; the simulator's camera paths), then
`orchard-map run front back --out ...` and `orchard-map evaluate --json` run on it as a user would. One table
per row: per side trunks found (recall, precision vs the truth), diameter MAE and bias, drift and ATE in % of
the path; the merge's outcome (exit code, rotation / translation error, merged map error) and run times.
`--fruit LO HI`: LO-HI fruit per tree hung in the crowns' outer shell (this renderer's own fruit look: a
mottled blush over a yellow-green ground, or green to yellow-green) and the run made with `fruit.enabled=true`:
the row's fruit count against the fruit visible from either side, the per-tree count error (median), fruit
counted twice per 100 seen from both sides, position and diameter errors.

Usage:
  python benchmarks/unseen_rows.py [--rows 2] [--trees 6] [--seed 0] [--rate 10] [--motions standard handheld_walk]
        [--workdir DIR (default: the system temporary folder/unseen_rows)] [--reuse] [--json benchmarks/results/unseen_rows.json] [--set key=value ...]
        [--fruit 20 40]

Row k uses seed (seed + k) and motion motions[k % len(motions)] (default: row 0 steady, row 1 hand-held).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from orchard_mapping.io.results import portable_json
from orchard_mapping.sim.scan_row_scene import ScanRowSpec
from orchard_mapping.sim.scan_rows import generate_scan_row

ROOT = Path(__file__).resolve().parents[1]
CLI = str(Path(sys.executable).with_name("orchard-map"))


def _fmt(v: Any, nd: int = 1, suffix: str = "") -> str:
    return "n/a" if v is None else f"{v:.{nd}f}{suffix}"


def _product_state() -> dict[str, Any]:
    """The commit the product ran at and the tracked files under orchard_mapping/ modified in the working tree
    (other people's uncommitted edits are picked up by the editable install)."""
    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    return {"head": git("rev-parse", "--short", "HEAD"),
            "modified": git("status", "--porcelain", "--untracked-files=no", "--", "orchard_mapping").splitlines()}


def run_row(k: int, args: argparse.Namespace, console: Console) -> dict[str, Any]:
    motion = args.motions[k % len(args.motions)]
    seed = args.seed + k
    row_dir = Path(args.workdir) / f"row{k}_{motion}_seed{seed}{'_fruit' if args.fruit else ''}"
    sim_dir, out_dir = row_dir / "sim", row_dir / "out"
    spec = ScanRowSpec(n_trees=args.trees, motion=motion, rate_hz=args.rate,
                       fruit_per_tree=tuple(args.fruit) if args.fruit else (0, 0))
    rec: dict[str, Any] = {"row": k, "motion": motion, "seed": seed, "trees": args.trees, "rate_hz": args.rate,
                           "dir": str(row_dir), "product": _product_state()}
    if args.reuse and (sim_dir / "ground_truth.json").is_file():
        rec["generate_s"] = None
    else:
        t = time.perf_counter()
        res = generate_scan_row(sim_dir, seed=seed, spec=spec, force=True)
        rec["generate_s"] = round(time.perf_counter() - t, 1)
        rec["frames"] = res.frames
        console.print(f"row {k}: generated {res.frames} frames in {rec['generate_s']} s")
    cmd = [CLI, "run", str(sim_dir / "front"), str(sim_dir / "back"), "--out", str(out_dir)]
    for s in (["fruit.enabled=true"] if args.fruit else []) + args.set:
        cmd += ["--set", s]
    if not (args.reuse and (out_dir / "timings.json").is_file()):
        t = time.perf_counter()
        p = subprocess.run(cmd, capture_output=True, text=True)
        rec["run_s"] = round(time.perf_counter() - t, 1)
        rec["run_exit"] = p.returncode
        rec["run_tail"] = (p.stdout + p.stderr)[-1500:]
        console.print(f"row {k}: orchard-map run exit {p.returncode} in {rec['run_s']} s")
    ev = subprocess.run([CLI, "evaluate", "--truth", str(sim_dir / "ground_truth.json"), "--result", str(out_dir),
                         "--json"], capture_output=True, text=True)
    rec["evaluate_exit"] = ev.returncode
    try:
        rec["evaluation"] = json.loads(ev.stdout)
    except json.JSONDecodeError:
        rec["evaluation"] = None
        rec["evaluate_tail"] = (ev.stdout + ev.stderr)[-1500:]
    return rec


def summarise(rec: dict[str, Any]) -> dict[str, Any]:
    ev = rec.get("evaluation") or {}
    out: dict[str, Any] = {"sides": {}}
    for side in ("front", "back"):
        tr = (ev.get("trunks") or {}).get(side) or {}
        sd = (ev.get("sides") or {}).get(side) or {}
        out["sides"][side] = {
            "trunks_true_in_view": tr.get("true_in_view"), "trunks_reported": tr.get("reported"),
            "trunks_matched": tr.get("matched"), "recall": tr.get("recall"), "precision": tr.get("precision"),
            "diameter_mae_mm": tr.get("diameter_mae_mm"), "diameter_bias_mm": tr.get("diameter_bias_mm"),
            "diameter_n": tr.get("diameter_n"), "axis_error_deg": tr.get("axis_error_deg"),
            "drift_percent": sd.get("drift_percent"), "ate_percent": sd.get("ate_percent"),
            "path_length_m": sd.get("path_length_m"),
        }
    m = ev.get("merge")
    out["merge"] = {
        "succeeded": rec.get("run_exit") == 0 and m is not None,
        "run_exit": rec.get("run_exit"),
        "rotation_error_deg": None if m is None else m.get("rotation_error_deg"),
        "translation_error_mm": None if m is None else m.get("translation_error_mm"),
        "map_trunk_sweep": None if m is None else m.get("map_trunk_sweep"),
        "skipped": (ev.get("skipped") or {}).get("merge"),
    }
    mt = ev.get("matching") or {}
    tr = ev.get("traits") or {}
    out["trees"] = {"matched": mt.get("matched"), "true": mt.get("true_trees"), "false": mt.get("false"),
                    "diameter_mae_mm": tr.get("trunk_diameter_mae_mm"), "position_rmse_mm": mt.get("position_rmse_mm")}
    fc, dc = ev.get("fruit_count") or {}, ev.get("double_count") or {}
    per_tree = [abs(p["est_fruit_count"] - p["true_fruit_visible"]) / p["true_fruit_visible"] * 100
                for p in ev.get("per_tree") or [] if p.get("est_fruit_count") is not None and p["true_fruit_visible"]]
    out["fruit"] = None if not fc else {
        "counted": fc.get("estimated"), "true_visible": fc.get("true_visible"), "true_all": fc.get("true_all"),
        "error_visible_percent": fc.get("error_visible_percent"),
        "per_tree_error_median_percent": round(float(statistics.median(per_tree)), 1) if per_tree else None,
        "twice_per_100_seen_from_both": dc.get("per_both_percent"), "false": dc.get("false"),
        "position_error_median_mm": dc.get("position_error_median_mm"), "diameter_mae_mm": dc.get("diameter_mae_mm"),
        "diameter_bias_mm": dc.get("diameter_bias_mm")}
    return out


def table(rec: dict[str, Any], s: dict[str, Any]) -> Table:
    t = Table(title=f"row {rec['row']}: {rec['motion']}, seed {rec['seed']}, {rec['trees']} real trees, "
                    f"{rec['rate_hz']:g} Hz (generate {rec.get('generate_s')} s, run {rec.get('run_s')} s)")
    for c in ("side", "trunks found", "recall", "precision", "diam MAE mm", "bias mm", "axis deg", "drift %",
              "ATE %"):
        t.add_column(c, justify="right")
    for side, v in s["sides"].items():
        t.add_row(side, f"{v['trunks_matched']}/{v['trunks_true_in_view']} ({v['trunks_reported']} reported)",
                  _fmt(v["recall"], 2), _fmt(v["precision"], 2), _fmt(v["diameter_mae_mm"], 2),
                  _fmt(v["diameter_bias_mm"], 2), _fmt(v["axis_error_deg"], 2), _fmt(v["drift_percent"], 2),
                  _fmt(v["ate_percent"], 2))
    m = s["merge"]
    mm = m["map_trunk_sweep"] or {}
    t.caption = (f"merge: {'ok' if m['succeeded'] else 'FAILED'} (run exit {m['run_exit']}); "
                 f"T_front_back error {_fmt(m['rotation_error_deg'], 3)} deg / {_fmt(m['translation_error_mm'])} mm; "
                 f"merged map (trunk sweeps) {_fmt(mm.get('rotation_error_deg'), 3)} deg / "
                 f"{_fmt(mm.get('translation_error_mm'))} mm; trees matched {s['trees']['matched']}/{s['trees']['true']}"
                 f" (false {s['trees']['false']}), two-side diameter MAE {_fmt(s['trees']['diameter_mae_mm'], 2)} mm"
                 + (f"; merge skipped: {m['skipped']}" if m["skipped"] and not m["succeeded"] else ""))
    f = s.get("fruit")
    if f:
        t.caption += (f"\nfruit: {f['counted']} counted of {f['true_visible']} visible ({f['true_all']} on the trees): "
                      f"{_fmt(f['error_visible_percent'], 1, ' %')}; per-tree error (median) "
                      f"{_fmt(f['per_tree_error_median_percent'], 1, ' %')}; twice per 100 seen from both "
                      f"{_fmt(f['twice_per_100_seen_from_both'], 1)}; false {f['false']}; position "
                      f"{_fmt(f['position_error_median_mm'], 1, ' mm')}; diameter MAE {_fmt(f['diameter_mae_mm'], 1, ' mm')}"
                      f" (bias {_fmt(f['diameter_bias_mm'], 1, ' mm')})")
    return t


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, default=2)
    ap.add_argument("--trees", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--motions", nargs="+", default=["standard", "handheld_walk"])
    ap.add_argument("--workdir", default=str(Path(tempfile.gettempdir()) / "unseen_rows"))
    ap.add_argument("--reuse", action="store_true", help="reuse generated rows and results in --workdir")
    ap.add_argument("--json", default=None, help="results JSON (default benchmarks/results/unseen_rows_<...>.json)")
    ap.add_argument("--set", action="append", default=[], help="config override passed to orchard-map run")
    ap.add_argument("--fruit", type=int, nargs=2, default=None, metavar=("LO", "HI"),
                    help="hang LO-HI fruit per tree and run the fruit stage")
    args = ap.parse_args(argv)
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    console = Console(width=150)
    records = []
    for k in range(args.rows):
        rec = run_row(k, args, console)
        rec["summary"] = summarise(rec)
        console.print(table(rec, rec["summary"]))
        if rec.get("run_exit") not in (0, None):
            console.print(rec.get("run_tail", "")[-600:])
        records.append(rec)
    path = Path(args.json) if args.json else ROOT / "benchmarks" / "results" / (
        f"unseen_rows_{args.trees}trees_{'_'.join(args.motions[:args.rows])}_seed{args.seed}"
        f"{'_fruit' if args.fruit else ''}.json")
    path.parent.mkdir(parents=True, exist_ok=True)
    slim = [{k: v for k, v in r.items() if k != "evaluation"} | {"evaluation": r.get("evaluation")} for r in records]
    path.write_text(portable_json({"benchmark": "unseen_rows", "args": vars(args), "rows": slim}, indent=1))
    console.print(f"results: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
