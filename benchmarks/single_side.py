"""Single-side reconstruction vs a dense Open3D RGB-D odometry baseline, on simulated rows.

For each (scenario, number of trees): simulate the row once (both sides, 640x480 at --rate Hz),
then in the same process, one after the other on the same bags:

(a) our pipeline (`orchard_mapping.pipeline.run`, default config): per side the drift % and ATE
    (% of the path, mm) of the keyframe trajectory after loop closure + BA (trajectory_<side>.tum)
    and of the front end alone (odometry_<side>.tum), the verified loops, the front-end time per
    frame (median of `RGBDFrontEnd.track` calls, timed by wrapping the method during the run; the
    mean of timings.json front_end_<side> / frames also counts bag decoding), BA and fusion
    seconds, and the real-time factor (processing seconds of the side's stages / recording seconds);
(b) the Open3D dense baseline (`core.dense_odometry`, frame to frame, each --baseline method) on
    every frame of the same bags: drift %, ATE % / mm, median ms per frame pair (Open3D calls
    only) and its real-time factor (including bag decoding);
(c) ratios ours / baseline for drift and ATE (< 1: ours is better).

Drift and ATE follow orchard_mapping.eval.metrics.trajectory_error (drift = last-pose position
error after aligning the first pose, % of the true path length; ATE = RMSE after a rigid Umeyama
fit). The baseline is scored at our keyframe stamps, so both are measured over the same poses and
span; its all-frame numbers are in the JSON too.

    python benchmarks/single_side.py --quick                      # 2 trees, standard: smoke run
    python benchmarks/single_side.py --matrix [--quick] [--trees 10]  # every scenario at 15/30 Hz (+10 Hz)
    python benchmarks/single_side.py --matrix --json m.json --resume  # in parts: keeps finished cases
    python benchmarks/single_side.py --table benchmarks/results/single_side_matrix_10trees.json  # print it again
    python benchmarks/single_side.py --trees 10 30 --scenarios standard wind [--rate 15] [--seed 0]
        [--workdir DIR] [--reuse] [--baseline point_to_plane hybrid] [--json results.json]

--reuse skips simulating a case whose folder already holds a simulation (same scenario, trees,
rate, seed). Timings are wall-clock on whatever machine runs this: compare within one run.
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
from rich.console import Console
from rich.logging import RichHandler
from rich.table import Table

from orchard_mapping import pipeline
from orchard_mapping.config import OrchardConfig, load_config
from orchard_mapping.core import odometry as odometry_module
from orchard_mapping.core.dense_odometry import dense_rgbd_odometry_result
from orchard_mapping.core.geometry import matrix_to_quat
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.eval import evaluate_result
from orchard_mapping.eval.ground_truth import load_ground_truth
from orchard_mapping.eval.metrics import associate_stamps, trajectory_error
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.io.results import portable_json, read_tum
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import simulate

SIDES = ("front", "back")
FRONT_ENDS: list[Any] = []  # the front ends of the last pipeline run (timed_track)
console = Console(width=150)
# --matrix: every scenario in config/scenarios/ at 15 and 30 Hz, plus these at 10 Hz (the hand-held issue).
MATRIX_RATES = (15.0, 30.0)
MATRIX_10HZ = ("standard", "tilted")


# ------------------------------------------------------------------------------------------ helpers


@contextmanager
def timed_track() -> Iterator[dict[int, list[tuple[float, bool]]]]:
    """Wrap RGBDFrontEnd.track: per front-end instance (in order of creation) (seconds, placed) per frame.
    The instances themselves are in FRONT_ENDS (same order), for their events and counters."""
    calls: dict[int, list[tuple[float, bool]]] = {}
    FRONT_ENDS.clear()
    original = odometry_module.RGBDFrontEnd.track

    def track(self, frame):  # type: ignore[no-untyped-def]
        t0 = time.perf_counter()
        pose = original(self, frame)
        if id(self) not in calls:
            FRONT_ENDS.append(self)
        calls.setdefault(id(self), []).append((time.perf_counter() - t0, bool(np.isfinite(pose).all())))
        return pose

    odometry_module.RGBDFrontEnd.track = track  # type: ignore[method-assign]
    try:
        yield calls
    finally:
        odometry_module.RGBDFrontEnd.track = original  # type: ignore[method-assign]


def _trajectory(stamps: np.ndarray, poses: np.ndarray) -> StampedTrajectory:
    q = np.array([matrix_to_quat(T[:3, :3]) for T in poses])
    return StampedTrajectory(np.asarray(stamps, float), poses[:, :3, 3].copy(), q)


def _subset(traj: StampedTrajectory, stamps: np.ndarray) -> StampedTrajectory:
    """The poses of `traj` at (nearest within 5 ms of) `stamps`."""
    i, _ = associate_stamps(traj.stamps, np.asarray(stamps, float), 0.005)
    return StampedTrajectory(traj.stamps[i], traj.positions[i], traj.quaternions[i])


def _errors(est: StampedTrajectory, true: StampedTrajectory) -> dict[str, float | None]:
    te = trajectory_error(est, true)
    return {"drift_percent": te.drift_percent, "ate_percent": te.ate_percent, "ate_mm": te.ate_mm,
            "drift_mm": te.drift_mm, "final_rotation_error_deg": te.final_rotation_error_deg,
            "n_poses": te.n_associated}


def _ratio(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b else None


def _median_ms(seconds: list[float] | np.ndarray) -> float | None:
    return 1000.0 * float(np.median(seconds)) if len(seconds) else None


# ------------------------------------------------------------------------------------------ one case


def simulate_case(scenario: str, trees: int, rate: float, seed: int, sim_dir: Path, reuse: bool) -> float | None:
    """Simulate into sim_dir (seconds), or None when --reuse found a finished simulation there."""
    if reuse and (sim_dir / "ground_truth.json").is_file():
        console.log(f"reusing the simulation in {sim_dir}")
        return None
    sc = load_scenario(scenario, {"row.n_trees": trees, "camera.rate_hz": rate})
    last = [0.0]

    def progress(label: str, i: int, n: int) -> None:
        if i == n or time.perf_counter() - last[0] > 30:
            last[0] = time.perf_counter()
            console.log(f"simulate {scenario}/{trees} trees: {label} {i}/{n} frames")

    t0 = time.perf_counter()
    simulate(sc, seed, sim_dir, force=True, progress=progress)
    return time.perf_counter() - t0


def run_ours(sim_dir: Path, res_dir: Path, cfg: OrchardConfig) -> dict[str, Any]:
    gt = load_ground_truth(sim_dir / "ground_truth.json")
    console.log("running the pipeline (both sides)")
    t0 = time.perf_counter()
    with timed_track() as calls:
        if (sim_dir / "loop").is_dir():  # one bag round the row, frames labelled by side
            rr = pipeline.run(sim_dir / "loop", None, res_dir, cfg)
        else:
            rr = pipeline.run(sim_dir / "front", sim_dir / "back", res_dir, cfg)
    wall = time.perf_counter() - t0
    report = evaluate_result(sim_dir / "ground_truth.json", res_dir).to_dict()
    stages = dict(rr.timings.stages)
    # the front ends in order of creation, one per side; strict=False: a side without one is left out
    per_side_calls = dict(zip(SIDES, calls.values(), strict=False))
    per_side_fe = dict(zip(SIDES, FRONT_ENDS, strict=False))
    out: dict[str, Any] = {"wall_s": wall, "stages_s": stages, "realtime_factor": (report.get("timings") or {}).get(
        "realtime_factor"), "sides": {}}
    for side in SIDES:
        sm = rr.sides[side]
        ev = report["sides"][side] or {}
        odo = _errors(read_tum(res_dir / f"odometry_{side}.tum"), gt.sides[side].trajectory)
        track = per_side_calls.get(side, [])
        n_frames = len(track)
        side_stages = {k: v for k, v in stages.items() if k.endswith(f"_{side}")}
        dur = gt.sides[side].duration_s
        fe = per_side_fe.get(side)
        # the front end's own words for every loss, relocalisation and restart (to explain each one)
        events = [e for e in getattr(fe, "events", [])
                  if "lost" in e or "relocalised" in e or "recovered" in e or "restarted" in e]
        out["sides"][side] = {
            "drift_percent": ev.get("drift_percent"), "ate_percent": ev.get("ate_percent"), "ate_mm": ev.get("ate_mm"),
            "drift_mm": ev.get("drift_mm"), "final_rotation_error_deg": ev.get("final_rotation_error_deg"),
            "odometry": odo,
            "keyframes": len(sm.keyframe_stamps),
            "keyframe_stamps": sm.keyframe_stamps.tolist(),
            "frames": n_frames,
            "frames_unplaced": sum(1 for _, ok in track if not ok),
            "lost_frames": getattr(fe, "lost_frames", None),
            "relocalisations": sum("relocalised" in e or "recovered" in e for e in events),
            "restarts": sum("restarted" in e for e in events),
            "events": events,
            "retracked_frames": getattr(fe, "retracked_frames", None),
            "loops": len(sm.loops),
            "track_ms_median": _median_ms([s for s, _ in track]),
            "track_ms_p90": 1000.0 * float(np.percentile([s for s, _ in track], 90)) if track else None,
            "front_end_ms_per_frame": 1000.0 * stages.get(f"front_end_{side}", 0.0) / n_frames if n_frames else None,
            "loop_detection_s": stages.get(f"loop_detection_{side}"),
            "pose_graph_s": stages.get(f"pose_graph_{side}"),
            "ba_s": stages.get(f"bundle_adjustment_{side}"),
            "fusion_s": stages.get(f"fusion_{side}"),
            "processing_s": sum(side_stages.values()),
            "recording_s": dur,
            "path_length_m": gt.sides[side].path_length_m,
            "realtime_factor": sum(side_stages.values()) / dur if dur > 0 else None,
        }
    return out


def run_baseline(sim_dir: Path, cfg: OrchardConfig, method: str, ours: dict[str, Any]) -> dict[str, Any]:
    gt = load_ground_truth(sim_dir / "ground_truth.json")
    inp = cfg.input
    out: dict[str, Any] = {"method": method, "sides": {}}
    for side in SIDES:
        console.log(f"Open3D dense baseline ({method}), {side} side")
        seq = read_rgbd(sim_dir / side, inp.topics, mode="rgbd", max_pair_dt_s=inp.max_pair_dt_s,
                        depth_min_m=inp.depth_min_m, depth_max_m=inp.depth_max_m)
        t0 = time.perf_counter()
        r = dense_rgbd_odometry_result(iter(seq), method=method)  # type: ignore[arg-type]
        total = time.perf_counter() - t0
        traj = _trajectory(r.stamps, r.poses)
        true = gt.sides[side].trajectory
        at_kf = _errors(_subset(traj, np.array(ours["sides"][side]["keyframe_stamps"])), true)
        dur = gt.sides[side].duration_s
        out["sides"][side] = {
            **{k: at_kf[k] for k in ("drift_percent", "ate_percent", "ate_mm", "drift_mm", "final_rotation_error_deg")},
            "scored_poses": at_kf["n_poses"],
            "all_frames": _errors(traj, true),
            "frames": len(r.stamps),
            "failed_pairs": len(r.failed_pairs),
            "pair_ms_median": _median_ms(r.pair_seconds),
            "pair_ms_p90": 1000.0 * float(np.percentile(r.pair_seconds, 90)) if len(r.pair_seconds) else None,
            "processing_s": total,
            "realtime_factor": total / dur if dur > 0 else None,
        }
    return out


def _case_dir(workdir: Path, scenario: str, trees: int, rate: float, seed: int) -> Path:
    return workdir / f"{scenario}_{trees}trees_{rate:g}hz_seed{seed}"


def run_case(scenario: str, trees: int, rate: float, seed: int, workdir: Path, reuse: bool,
             baselines: list[str]) -> dict[str, Any]:
    case_dir = _case_dir(workdir, scenario, trees, rate, seed)
    sim_dir, res_dir = case_dir / "sim", case_dir / "result"
    console.rule(f"{scenario}, {trees} trees, {rate:g} Hz, seed {seed}")
    sim_s = simulate_case(scenario, trees, rate, seed, sim_dir, reuse)
    cfg = load_config()
    ours = run_ours(sim_dir, res_dir, cfg)
    base = {m: run_baseline(sim_dir, cfg, m, ours) for m in baselines}
    ratios = {m: {side: {"drift": _ratio(ours["sides"][side]["drift_percent"], b["sides"][side]["drift_percent"]),
                         "ate": _ratio(ours["sides"][side]["ate_percent"], b["sides"][side]["ate_percent"]),
                         "odometry_drift": _ratio(ours["sides"][side]["odometry"]["drift_percent"],
                                                  b["sides"][side]["drift_percent"]),
                         "odometry_ate": _ratio(ours["sides"][side]["odometry"]["ate_percent"],
                                                b["sides"][side]["ate_percent"])}
                  for side in SIDES}
              for m, b in base.items()}
    for side in SIDES:  # keep the JSON readable
        ours["sides"][side].pop("keyframe_stamps")
    return {"scenario": scenario, "trees": trees, "rate_hz": rate, "seed": seed, "folder": str(case_dir),
            "simulate_s": sim_s, "ours": ours, "baselines": base, "ratios": ratios}


# ------------------------------------------------------------------------------------------ tables


def _f(v: float | None, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def _g(v: float | None) -> str:
    return "-" if v is None else f"{v:.2g}"


def case_table(case: dict[str, Any]) -> Table:
    t = Table(title=f"{case['scenario']}, {case['trees']} trees, {case['rate_hz']:g} Hz, seed {case['seed']}",
              title_justify="left")
    for col, just in [("side", "left"), ("method", "left"), ("drift %", "right"), ("ATE %", "right"),
                      ("ATE mm", "right"), ("frames", "right"), ("kf / loops", "right"),
                      ("ms/frame", "right"), ("BA s", "right"), ("fusion s", "right"), ("RTF", "right")]:
        t.add_column(col, justify=just)  # type: ignore[arg-type]
    o = case["ours"]["sides"]
    for k, side in enumerate(SIDES):
        s = o[side]
        t.add_row(side, "ours (loops + BA)", _f(s["drift_percent"]), _f(s["ate_percent"]), _f(s["ate_mm"], 1),
                  f"{s['frames']}" + (f" ({s['frames_unplaced']} lost)" if s["frames_unplaced"] else ""),
                  f"{s['keyframes']} / {s['loops']}", _f(s["track_ms_median"], 1), _f(s["ba_s"], 1),
                  _f(s["fusion_s"], 1), _f(s["realtime_factor"], 2))
        od = s["odometry"]
        t.add_row("", "ours front end only", _f(od["drift_percent"]), _f(od["ate_percent"]), _f(od["ate_mm"], 1),
                  "", "", f"({_f(s['front_end_ms_per_frame'], 1)})", "", "", "")
        for m, b in case["baselines"].items():
            bs = b["sides"][side]
            t.add_row("", f"Open3D {m}", _f(bs["drift_percent"]), _f(bs["ate_percent"]), _f(bs["ate_mm"], 1),
                      f"{bs['frames']}" + (f" ({bs['failed_pairs']} failed)" if bs["failed_pairs"] else ""),
                      "", _f(bs["pair_ms_median"], 1), "", "", _f(bs["realtime_factor"], 2))
        for m, r in case["ratios"].items():
            rs = r[side]
            t.add_row("", f"ratio ours / {m}", _g(rs["drift"]), _g(rs["ate"]), "", "", "", "", "", "", "",
                      style="bold")
        if k < len(SIDES) - 1:
            t.add_section()
    return t


SHORT = {"point_to_plane": "p2p", "hybrid": "hybrid", "intensity": "intensity"}


def matrix_table(cases: list[dict[str, Any]]) -> Table:
    """One row per case and side: accuracy after BA, losses, relocalisations, speed."""
    t = Table(title="Single-side reconstruction per scenario and rate (after loops + BA; front end alone in "
                    "brackets)", title_justify="left")
    for col in ("scenario", "Hz", "trees", "side", "drift %", "ATE %", "lost", "reloc", "restart", "retracked",
                "ms/frame", "RTF"):
        t.add_column(col, justify="left" if col in ("scenario", "side") else "right", no_wrap=True)
    for c in cases:
        for side in SIDES:
            s = c["ours"]["sides"][side]
            od = s["odometry"]
            t.add_row(c["scenario"], f"{c['rate_hz']:g}", str(c["trees"]), side,
                      f"{_f(s['drift_percent'])} ({_f(od['drift_percent'])})",
                      f"{_f(s['ate_percent'])} ({_f(od['ate_percent'])})",
                      str(s["lost_frames"]), str(s["relocalisations"]), str(s["restarts"]),
                      str(s["retracked_frames"]), _f(s["track_ms_median"], 1), _f(s["realtime_factor"], 2))
    return t


def summary_table(cases: list[dict[str, Any]]) -> Table:
    methods = list(cases[0]["baselines"])
    t = Table(title="Summary: drift % / ATE % per side; ratio = ours / Open3D (< 1: ours better); "
                    "ms per frame: ours track / Open3D " + " / ".join(SHORT[m] for m in methods), title_justify="left")
    for col in ("case", "side", "ours", "ours FE", *(f"O3D {SHORT[m]}" for m in methods),
                *(f"ratio {SHORT[m]}" for m in methods), "ms/frame", "RTF ours"):
        t.add_column(col, justify="left" if col in ("case", "side") else "right", no_wrap=True)
    for c in cases:
        for side in SIDES:
            s = c["ours"]["sides"][side]
            base = [c["baselines"][m]["sides"][side] for m in methods]
            rat = [c["ratios"][m][side] for m in methods]
            t.add_row(f"{c['scenario']} {c['trees']}t", side,
                      f"{_f(s['drift_percent'])} / {_f(s['ate_percent'])}",
                      f"{_f(s['odometry']['drift_percent'])} / {_f(s['odometry']['ate_percent'])}",
                      *(f"{_f(b['drift_percent'])} / {_f(b['ate_percent'])}" for b in base),
                      *(f"{_g(r['drift'])} / {_g(r['ate'])}" for r in rat),
                      " / ".join([_f(s["track_ms_median"], 0)] + [_f(b["pair_ms_median"], 0) for b in base]),
                      _f(s["realtime_factor"], 2))
    return t


# ------------------------------------------------------------------------------------------ main


def _commit() -> str:
    """What the numbers belong to: the commit and the git tree ids of the product's code and config
    ('code <orchard_mapping>-<config>'), so that a commit that touches only docs, tests or benchmarks
    keeps the finished cases; '+modified' when the working tree's code or config differs from HEAD."""
    root = Path(__file__).resolve().parents[1]

    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=root, capture_output=True, text=True, check=True).stdout.strip()

    try:
        head = git("rev-parse", "--short", "HEAD")
        code = "-".join(git("rev-parse", "--short", f"HEAD:{d}") for d in ("orchard_mapping", "config"))
        dirty = git("status", "--porcelain", "--", "orchard_mapping", "config")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return f"{head} code {code}" + ("+modified" if dirty else "")


def _code(commit: str) -> str:
    return commit.split(" code ", 1)[-1]


def _finished_cases(path: Path, commit: str) -> dict[tuple[str, int, float, int], dict[str, Any]]:
    """Cases a previous --json run measured on the same code and config (clean tree), by
    (scenario, trees, Hz, seed)."""
    if not path.is_file() or commit == "unknown" or commit.endswith("+modified"):
        return {}
    return {(c["scenario"], c["trees"], float(c["rate_hz"]), c["seed"]): c
            for c in json.loads(path.read_text())["cases"] if _code(c.get("commit", "")) == _code(commit)}


def _write_json(path: Path, cases: list[dict[str, Any]]) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(portable_json({"cases": cases}, indent=1))
    tmp.replace(path)  # atomic: an interrupted run never leaves half a file


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trees", type=int, nargs="+", default=[10, 30])
    ap.add_argument("--scenarios", nargs="+", default=["standard", "wind"])
    ap.add_argument("--rate", type=float, default=15.0, help="camera rate (Hz)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "orchard_single_side")
    ap.add_argument("--reuse", action="store_true", help="skip simulating when the case folder holds a simulation")
    ap.add_argument("--baseline", nargs="+", default=None,
                    choices=["point_to_plane", "hybrid", "intensity"], help="Open3D odometry method(s)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: 2 trees, standard scenario only (with --matrix: 3 trees, standard, tilted, "
                         "handheld_walk and vehicle at 15 Hz, and tilted at 10 Hz)")
    ap.add_argument("--matrix", action="store_true",
                    help="every scenario in config/scenarios/ at 15 and 30 Hz, standard and tilted also at 10 Hz "
                         "(10 trees unless --trees); one table with losses and relocalisations; no baseline unless "
                         "--baseline is given")
    ap.add_argument("--json", type=Path, default=None, help="write every number to this JSON file")
    ap.add_argument("--resume", action="store_true",
                    help="with --json: keep the cases that file already holds from the same code and config (clean tree) "
                         "instead of running them again, so a matrix of several hours can be run in parts")
    ap.add_argument("--only-simulated", action="store_true",
                    help="with --reuse: run only the cases whose folder already holds a simulation (simulate the "
                         "others elsewhere meanwhile, then --resume)")
    ap.add_argument("--verbose", "-v", action="store_true", help="show the pipeline's warnings (relocalisations, ...)")
    ap.add_argument("--table", type=Path, metavar="JSON",
                    help="print the tables of a results JSON (e.g. benchmarks/results/*.json) and exit")
    args = ap.parse_args(argv)
    if args.table is not None:
        cases = json.loads(args.table.read_text())["cases"]
        console.print(matrix_table(cases))
        for c in cases:
            for side in SIDES:
                for e in c["ours"]["sides"][side].get("events", []):
                    console.print(f"{c['scenario']} {c['rate_hz']:g} Hz {side}: {e}")
        commits = sorted({c.get("commit", "?") for c in cases})
        console.print(f"{len(cases)} cases from {args.table}; measured at {', '.join(commits)}")
        return 0
    trees_given = args.trees != ap.get_default("trees")
    if args.matrix:
        from orchard_mapping.sim.scenario import list_scenarios

        args.baseline = args.baseline or []
        if args.quick:
            runs = [(sc, 15.0) for sc in ("standard", "tilted", "handheld_walk", "vehicle")] + [("tilted", 10.0)]
            args.trees = args.trees if trees_given else [3]
        else:
            runs = [(sc, r) for sc in list_scenarios() for r in MATRIX_RATES] + [(sc, 10.0) for sc in MATRIX_10HZ]
            args.trees = args.trees if trees_given else [10]
    else:
        args.baseline = args.baseline if args.baseline is not None else ["point_to_plane", "hybrid"]
        if args.quick:
            args.trees, args.scenarios = [2], ["standard"]
        runs = [(sc, args.rate) for sc in args.scenarios]
    logging.basicConfig(level=logging.WARNING, handlers=[RichHandler(console=console, show_path=False)],
                        format="%(name)s: %(message)s")
    if not args.verbose:  # the front end logs every relocalisation as a warning: too many for a table run
        logging.getLogger("orchard_mapping").setLevel(logging.ERROR)
    args.workdir.mkdir(parents=True, exist_ok=True)
    commit = _commit()
    done = _finished_cases(args.json, commit) if args.resume and args.json else {}
    cases = []
    t0 = time.perf_counter()
    for scenario, rate in runs:
        for trees in args.trees:
            key = (scenario, trees, float(rate), args.seed)
            if key in done:
                console.print(f"{scenario}, {trees} trees, {rate:g} Hz: kept from {args.json} (commit {commit})")
                cases.append(done[key])
                continue
            sim_dir = _case_dir(args.workdir, scenario, trees, rate, args.seed) / "sim"
            if args.only_simulated and not (sim_dir / "ground_truth.json").is_file():
                console.print(f"{scenario}, {trees} trees, {rate:g} Hz: not simulated yet in {sim_dir}, skipped")
                continue
            case = run_case(scenario, trees, rate, args.seed, args.workdir, args.reuse, args.baseline)
            case["commit"] = commit
            cases.append(case)
            console.print(case_table(case))
            if args.json:  # after every case, so a long run keeps what it has
                _write_json(args.json, cases)
    console.rule("summary")
    console.print(matrix_table(cases))
    if args.baseline:
        console.print(summary_table(cases))
    console.print("ms/frame: ours = median RGBDFrontEnd.track call (in brackets: front_end stage / frames, "
                  "with bag decoding); Open3D = median odometry call per frame pair. RTF = processing s / "
                  "recording s of that side (ours: front end + loops + pose graph + BA + fusion). Baseline "
                  "scored at our keyframe stamps.")
    console.print(f"total {time.perf_counter() - t0:.0f} s; cases in {args.workdir}")
    if args.json:
        _write_json(args.json, cases)
        console.print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
