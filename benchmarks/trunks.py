"""Trunks and local grounds on simulated 10-tree rows: accuracy, the paper's baselines, cost.

For each scenario (default: standard and slope_weeds, 10 trees, 15 Hz, seed 0) the row is simulated
once with instance masks, then the `orchard-map run` command reconstructs both sides with trunks
(--source masks: the simulator's masks, the geometry without detector errors; --source model: the
ONNX detector at trunks.model). Printed in one table per side:

  - trunk recall / precision, diameter MAE and bias with eq. objectCylinder's 2D term and with the
    3D-only fit of the same bands (the paper's baseline), axis error (orchard-map evaluate's metrics);
  - local ground: normal and height error with the trunk-axis prior (ours) and with plain RANSAC
    (Open3D segment_plane on the same candidate points), median and max over trees, and the number of
    trees where each is off by more than 5 deg or 3 cm;
  - seconds of the trunk stage per side, detector ms per frame (with --source model).

With --cost (standard only), the same row is also run with trunks.source=off, alternating the two
configurations --repeat times, and the ratio of the runs' wall-clock times (with / without) is printed:
the goal is <= 1.25. The run without trunks has no merge (it needs trunks), so the ratio is also printed
with the merge stage's time (it comes last, outputs included) taken off the run with trunks.

With --set KEY=VALUE (repeatable, as `orchard-map run --set`) the run with trunks uses that configuration,
e.g. `--set trunks.flip_test=true --set trunks.detect_every_m=0.3`; its results go to `result_<--tag>`.

    python benchmarks/trunks.py [--scenarios standard slope_weeds] [--trees 10] [--rate 15]
        [--workdir DIR (default: the system temporary folder/trunks_bench)] [--reuse] [--source masks|model] [--cost --repeat 2] [--json out.json]
        [--set KEY=VALUE ...] [--tag NAME]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
from rich.console import Console
from rich.table import Table

from orchard_mapping.core.ground import GroundParams, fit_plane_plain_ransac, ground_neighbourhood
from orchard_mapping.eval import evaluate_result
from orchard_mapping.eval.ground_truth import load_ground_truth
from orchard_mapping.eval.landmarks import plane_errors, trunk_errors
from orchard_mapping.io.landmarks import read_grounds, read_trunks
from orchard_mapping.io.results import portable_json, read_timings, read_tum, trajectory_filename

console = Console()
SIDES = ("front", "back")


def simulate_case(scenario: str, trees: int, rate: float, seed: int, sim_dir: Path, reuse: bool) -> None:
    from orchard_mapping.sim.scenario import load_scenario
    from orchard_mapping.sim.simulate import simulate

    if reuse and (sim_dir / "ground_truth.json").is_file() and (sim_dir / "masks").is_dir():
        console.print(f"reusing {sim_dir}")
        return
    t0 = time.perf_counter()
    simulate(load_scenario(scenario, {"row.n_trees": trees, "camera.rate_hz": rate, "masks_every": 1}), seed,
             sim_dir, force=True)
    console.print(f"simulated {scenario} in {time.perf_counter() - t0:.0f} s")


def run_once(sim_dir: Path, out: Path, source: str, sets: Sequence[str] = ()) -> tuple[dict[str, float], float]:
    """(the run's stages, s; the wall-clock seconds of the whole `orchard-map run` command, its start and
    writing included). The command is what is timed, as a user runs it (its worker process and BLAS threads
    are set up there). Stages overlap (the detector beside the front end, the trunk worker), so they can add
    up to more than the run took."""
    cmd = [sys.executable, "-m", "orchard_mapping.cli.main", "run", str(sim_dir / "front"), str(sim_dir / "back"),
           "--out", str(out), "--set", f"trunks.source={source}"]
    if source == "masks":
        cmd += ["--set", f"trunks.masks_dir={sim_dir / 'masks'}"]
    for kv in sets:
        cmd += ["--set", kv]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return dict(read_timings(out).stages), wall


def plain_ransac_grounds(sim_dir: Path, res_dir: Path, seed: int) -> dict[str, list[tuple[float, float]]]:
    """Per side, (normal error deg, |height error| mm) of plain RANSAC on the same candidates as ours."""
    import open3d as o3d

    gt = load_ground_truth(sim_dir / "ground_truth.json")
    trunks = read_trunks(res_dir / "trunks.json")
    grounds = {(g.side, g.trunk_id) for g in read_grounds(res_dir / "grounds.json")}
    params = GroundParams()
    out: dict[str, list[tuple[float, float]]] = {}
    for side in SIDES:
        ts = gt.sides[side]
        est = read_tum(res_dir / trajectory_filename(side), ts.frame)
        pts = np.asarray(o3d.io.read_point_cloud(str(res_dir / f"{side}.ply")).points)
        _, links = trunk_errors(gt, side, trunks, est)
        errs = []
        for t in trunks:
            if t.side != side or t.id not in links or (side, t.id) not in grounds:
                continue
            tree, T = links[t.id]
            # the candidates ours used: the disk around the axis, up to 0.3 m above the trunk's lowest point
            # (the base stands in for it here), the trunk's surface included (plain RANSAC has no trunk model)
            idx = ground_neighbourhood(pts, t.base, t.axis, params, trunk_bottom_height=0.0)
            fit = fit_plane_plain_ransac(pts[idx], params, seed, t.axis, t.base)
            if fit is None:
                continue
            seen = tree.seen_ground.get(side)
            ref = seen if seen is not None else (tree.ground_point, tree.ground_normal)
            n_e, h_e = plane_errors(T[:3, :3] @ fit.normal, T[:3, :3] @ fit.point + T[:3, 3], ref[0], ref[1])
            errs.append((n_e, abs(h_e)))
        out[side] = errs
    return out


def _f(v: float | None, d: int = 2) -> str:
    return "-" if v is None else f"{v:.{d}f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", nargs="+", default=["standard", "slope_weeds"])
    ap.add_argument("--trees", type=int, default=10)
    ap.add_argument("--rate", type=float, default=15.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "trunks_bench")
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--source", choices=("masks", "model"), default="masks")
    ap.add_argument("--cost", action="store_true", help="standard: time the run with and without trunks")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="configuration override for the run with trunks (as orchard-map run --set)")
    ap.add_argument("--tag", help="results in result_<tag> (default: result)")
    args = ap.parse_args(argv)

    cases = []
    for sc in args.scenarios:
        case_dir = args.workdir / f"{sc}_{args.trees}trees_{args.rate:g}hz_seed{args.seed}"
        sim_dir = case_dir / "sim"
        res_dir = case_dir / (f"result_{args.tag}" if args.tag else "result")
        simulate_case(sc, args.trees, args.rate, args.seed, sim_dir, args.reuse)
        cost: dict[str, list[float]] = {"with": [], "without": [], "with_stage_sum": [], "without_stage_sum": [],
                                        "merge": []}
        if args.cost and sc == "standard":
            for _ in range(args.repeat):  # alternate, so that machine noise hits both alike
                off, wall = run_once(sim_dir, case_dir / "result_off", "off")
                cost["without"].append(wall)
                cost["without_stage_sum"].append(sum(off.values()))
                stages, wall = run_once(sim_dir, res_dir, args.source, args.sets)
                cost["with"].append(wall)
                cost["with_stage_sum"].append(sum(stages.values()))
                cost["merge"].append(stages.get("merge", 0.0))
        else:
            stages, _ = run_once(sim_dir, res_dir, args.source, args.sets)
        rep = evaluate_result(sim_dir / "ground_truth.json", res_dir).to_dict()
        plain = plain_ransac_grounds(sim_dir, res_dir, args.seed)
        cases.append({"scenario": sc, "trees": args.trees, "rate_hz": args.rate, "seed": args.seed,
                      "source": args.source, "sets": args.sets, "stages": stages, "trunks": rep["trunks"],
                      "grounds": rep["grounds"], "plain_ransac": plain, "cost_s": cost})

    tab = Table(title=f"trunks and local grounds ({args.source} masks), {args.trees} trees, {args.rate:g} Hz, "
                      f"seed {args.seed}" + (f", {' '.join(args.sets)}" if args.sets else ""), title_justify="left")
    for col in ("scenario", "side", "recall %", "precision %", "diam MAE mm (3D-only)", "diam bias mm (3D-only)",
                "axis deg", "ground deg med/max: prior | plain", "ground mm med/max: prior | plain",
                "trees off (>5 deg or >3 cm): prior | plain", "trunk stage s"):
        tab.add_column(col, justify="left" if col in ("scenario", "side") else "right")
    for c in cases:
        for side in SIDES:
            t, g, p = c["trunks"][side], c["grounds"][side], c["plain_ransac"][side]
            pn = [e[0] for e in p]
            ph = [e[1] for e in p]
            off_plain = sum(1 for n, h in p if n > 5 or h > 30)
            tab.add_row(
                c["scenario"], side, _f(100 * t["recall"] if t["recall"] is not None else None, 0),
                _f(100 * t["precision"] if t["precision"] is not None else None, 0),
                f"{_f(t['diameter_mae_mm'])} ({_f(t['diameter_3d_only_mae_mm'])})",
                f"{_f(t['diameter_bias_mm'])} ({_f(t['diameter_3d_only_bias_mm'])})",
                _f(t["axis_error_deg"]),
                f"{_f(g['normal_error_deg_median'])}/{_f(g['normal_error_deg_max'])} | "
                f"{_f(statistics.median(pn) if pn else None)}/{_f(max(pn) if pn else None)}",
                f"{_f(g['height_error_mm_median'], 1)}/{_f(g['height_error_mm_max'], 1)} | "
                f"{_f(statistics.median(ph) if ph else None, 1)}/{_f(max(ph) if ph else None, 1)}",
                f"{sum(1 for _, n, h in g['per_tree'] if n > 5 or abs(h) > 30)} of {g['n']} | {off_plain} of {len(p)}",
                _f(c["stages"].get(f"trunks_{side}")))
    console.print(tab)
    for c in cases:
        if c["cost_s"]["with"]:
            w, wo = statistics.median(c["cost_s"]["with"]), statistics.median(c["cost_s"]["without"])
            console.print(f"{c['scenario']}: `orchard-map run` with trunks {w:.1f} s, without {wo:.1f} s (wall clock, "
                          f"medians of {len(c['cost_s']['with'])} alternating runs): ratio {w / wo:.3f} (goal <= 1.25); "
                          f"stages added up: {statistics.median(c['cost_s']['with_stage_sum']):.1f} and "
                          f"{statistics.median(c['cost_s']['without_stage_sum']):.1f} s")
            if c["cost_s"].get("merge"):
                # the merge (and its outputs) ends the run: the run up to it is the trunk stage's own cost
                wm = statistics.median(a - m for a, m in zip(c["cost_s"]["with"], c["cost_s"]["merge"], strict=True))
                console.print(f"{c['scenario']}: without the two-side merge that trunks make possible (its "
                              f"{statistics.median(c['cost_s']['merge']):.1f} s and outputs), with trunks {wm:.1f} s: "
                              f"ratio {wm / wo:.3f}")
    if args.json:
        args.json.write_text(portable_json(cases, indent=1))
        console.print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
