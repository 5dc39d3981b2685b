"""Benchmark: the whole pipeline (`orchard-map run`: both sides, trunks, local grounds, merge, semantic BA)
on rows of growing length: time per stage, real-time factor, peak memory and accuracy in one table.

For each row length: simulate the `standard` row once (or reuse it), run `orchard-map run` on its two
bags in a child process whose resident memory (with its children) is sampled every 0.2 s, then
`orchard-map evaluate --json` against the simulator's truth. --code runs another checkout of the
project on the same bags (`git worktree add /tmp/before <rev>`), so a change is measured side by side
with the code before it in one run.

Usage:
  python benchmarks/scale.py [--trees 10 30] [--rate 15] [--seed 0] [--workdir /tmp/scale_bench]
        [--sim 30=/path/to/sim] [--sim-set camera.width=320 ... --tag half] [--code before=/tmp/before]
        [--json out.json]
  python benchmarks/scale.py --table out.json [more.json ...]

Rendering a row takes ~80 s per tree on 2 cores and ~180 MB of bags per tree (a 30-tree row: 40 min,
5.4 GB; a 100-tree row: ~2.2 h, 18 GB); --sim N=DIR reuses a simulation made elsewhere.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from orchard_mapping.io.results import portable_json

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import psutil  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# Stages of timings.json summed over both sides, in pipeline order (docs/results.md).
STAGES = ("read_bags", "front_end", "loop_detection", "pose_graph", "bundle_adjustment", "fusion",
          "trunk_detection", "trunks", "merge")


def _cli(code: Path | None) -> tuple[list[str], dict[str, str]]:
    """The command that starts `orchard-map` from a checkout (None: this one) and its environment."""
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    if code is None:
        return [sys.executable, "-m", "orchard_mapping.cli.main"], env
    env["PYTHONPATH"] = str(code)
    return [sys.executable, "-c", "import sys; from orchard_mapping.cli.main import app; sys.argv[0] = "
                                  "'orchard-map'; sys.exit(app())"], env


def run_sampled(cmd: list[str], env: dict[str, str], cwd: Path, log: Path, period_s: float = 0.2
                ) -> tuple[int, float, float]:
    """Run cmd; (exit code, wall s, peak resident memory MB of it and its children, sampled)."""
    t0 = time.perf_counter()
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
        p = psutil.Process(proc.pid)
        peak = 0
        while proc.poll() is None:
            try:
                rss = p.memory_info().rss + sum(c.memory_info().rss for c in p.children(recursive=True))
                peak = max(peak, rss)
            except psutil.Error:
                pass
            time.sleep(period_s)
    return proc.returncode, time.perf_counter() - t0, peak / 2**20


def simulate_row(trees: int, rate: float, seed: int, out: Path, settings: list[str]) -> Path:
    if not (out / "ground_truth.json").is_file():
        cmd, env = _cli(None)
        extra = [x for kv in settings for x in ("--set", kv)]
        subprocess.run(cmd + ["simulate", "--scenario", "standard", "--trees", str(trees), "--seed", str(seed),
                              "--set", f"camera.rate_hz={rate}", *extra, "--out", str(out), "--force"],
                       env=env, check=True)
    return out


def _figures(report: dict[str, Any]) -> dict[str, Any]:
    """The accuracy figures of an evaluation report (orchard-map evaluate --json) this table shows."""
    sides = report.get("sides", {})
    trunks = report.get("trunks", {})
    merge = report.get("merge") or {}
    gap = merge.get("trunk_axis_gap_mm") or {}
    return {
        "drift_percent": {s: sides[s]["drift_percent"] for s in sides},
        "ate_percent": {s: sides[s]["ate_percent"] for s in sides},
        "diameter_mae_mm": {s: trunks[s].get("diameter_mae_mm") for s in trunks},
        "merge_rotation_deg": merge.get("rotation_error_deg"),
        "merge_translation_mm": merge.get("translation_error_mm"),
        "gap_median_mm": gap.get("median"),
        "tree_rmse_mm": (report.get("trees") or {}).get("position_rmse_mm"),
    }


def measure(label: str, code: Path | None, sim: Path, trees: int, work: Path) -> dict[str, Any]:
    out = work / f"result_{label}_{trees}"
    cmd, env = _cli(code)
    rc, wall, peak = run_sampled(cmd + ["run", str(sim / "front"), str(sim / "back"), "--out", str(out)], env,
                                 code or ROOT, work / f"run_{label}_{trees}.log")
    if rc not in (0, 2):  # 2: the merge was refused, each side's results are complete (still measured)
        raise SystemExit(f"{label}, {trees} trees: orchard-map run exited {rc} (log {work}/run_{label}_{trees}.log)")
    timings = json.loads((out / "timings.json").read_text())
    stages: dict[str, float] = {}
    for name, s in timings["stages"].items():
        key = next((st for st in STAGES if name == st or name.startswith(st + "_")), name)
        stages[key] = stages.get(key, 0.0) + s
    ev = subprocess.run(cmd + ["evaluate", "--truth", str(sim / "ground_truth.json"), "--result", str(out), "--json"],
                        env=env, cwd=code or ROOT, capture_output=True, text=True, check=True)
    recorded = float(timings["recording_duration_s"])
    return {"label": label, "trees": trees, "frames": timings["frames"], "recorded_s": recorded,
            "processing_s": sum(timings["stages"].values()), "wall_s": wall, "peak_mb": peak,
            "rtf": sum(timings["stages"].values()) / recorded, "stages": stages, "merge_refused": rc == 2,
            **_figures(json.loads(ev.stdout))}


def _f(x: Any, fmt: str = ".2f") -> str:
    return "n/a" if x is None else format(x, fmt)


def print_table(rows: list[dict[str, Any]]) -> None:
    console = Console(width=220)
    t = Table(title="whole pipeline (orchard-map run) on simulated standard rows, 2 cores: time, memory")
    for c in ("code", "trees", "frames", "recorded s", "processing s", "RTF", "peak RSS GB",
              *(s.replace("_", " ") for s in STAGES)):
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(r["label"], str(r["trees"]), str(r["frames"]), _f(r["recorded_s"], ".1f"),
                  _f(r["processing_s"], ".1f"), _f(r["rtf"]), _f(r["peak_mb"] / 1024),
                  *(_f(r["stages"].get(s), ".1f") for s in STAGES))
    console.print(t)
    a = Table(title="accuracy against the simulator's truth (front / back)")
    for c in ("code", "trees", "drift %", "ATE %", "diameter MAE mm", "merge deg", "merge mm", "axis gap mm",
              "tree RMSE mm"):
        a.add_column(c, justify="right")
    for r in rows:
        a.add_row(r["label"] + (" (merge refused)" if r.get("merge_refused") else ""), str(r["trees"]),
                  " / ".join(_f(r["drift_percent"].get(s), ".3f") for s in ("front", "back")),
                  " / ".join(_f(r["ate_percent"].get(s), ".3f") for s in ("front", "back")),
                  " / ".join(_f(r["diameter_mae_mm"].get(s)) for s in ("front", "back")),
                  _f(r["merge_rotation_deg"], ".3f"), _f(r["merge_translation_mm"], ".1f"),
                  _f(r["gap_median_mm"]), _f(r["tree_rmse_mm"], ".1f"))
    console.print(a)
    by = {(r["label"], r["trees"]): r for r in rows}
    ts = sorted({r["trees"] for r in rows})
    for label in dict.fromkeys(r["label"] for r in rows):
        # each tree count with the next (ts[1:] is one shorter)
        pairs = [(n, m) for n, m in zip(ts, ts[1:], strict=False) if (label, n) in by and (label, m) in by]
        for n, m in pairs:
            console.print(f"{label}: {m} trees / {n} trees: time x{by[label, m]['processing_s'] / by[label, n]['processing_s']:.2f}, "
                          f"peak memory x{by[label, m]['peak_mb'] / by[label, n]['peak_mb']:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trees", type=int, nargs="+", default=[10, 30])
    ap.add_argument("--rate", type=float, default=15.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "scale_bench")
    ap.add_argument("--sim", action="append", default=[], metavar="N=DIR", help="reuse a simulated N-tree row")
    ap.add_argument("--sim-set", action="append", default=[], metavar="KEY=VALUE",
                    help="simulator setting for the rows simulated here (e.g. camera.width=320), named in --tag")
    ap.add_argument("--tag", default="", help="added to the simulated rows' folder names (their settings)")
    ap.add_argument("--code", action="append", default=[], metavar="LABEL=DIR",
                    help="also run another checkout of the project (e.g. before=/tmp/before)")
    ap.add_argument("--json", type=Path, help="write the rows here")
    ap.add_argument("--table", type=Path, nargs="+", help="only print the table of these JSON files")
    args = ap.parse_args()
    if args.table:
        print_table([r for p in args.table for r in json.loads(p.read_text())])
        return
    sims = {int(k): Path(v) for k, v in (s.split("=", 1) for s in args.sim)}
    codes: list[tuple[str, Path | None]] = [(k, Path(v)) for k, v in (c.split("=", 1) for c in args.code)]
    codes.append(("this", None))
    args.workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    for n in args.trees:
        name = f"standard_{n}trees_{args.rate:g}hz_seed{args.seed}" + (f"_{args.tag}" if args.tag else "")
        sim = sims.get(n) or simulate_row(n, args.rate, args.seed, args.workdir / name / "sim", args.sim_set)
        for label, code in codes:  # side by side: the same bags, one after the other, nothing else running
            rows.append(measure(label, code, sim, n, args.workdir))
            if args.json:
                tmp = args.json.with_suffix(".partial")
                tmp.write_text(portable_json(rows, indent=1))
                tmp.replace(args.json)
    print_table(rows)


if __name__ == "__main__":
    main()
