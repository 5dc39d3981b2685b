"""Benchmark: the RGB-D front end alone, its scale error and ATE per side, for front-end settings side by side.

For each simulated row (scenario, trees, seed; simulated once, or reused from --workdir) and each side,
the front end (core.odometry.RGBDFrontEnd, no loop closure, no bundle adjustment) places every frame
under each variant of the `odometry` settings; its keyframe positions are fitted to the true camera
positions (eval.metrics.trajectory_error) with a similarity and with a rigid transform:

- scale %: how much too long (+) or short (-) the side's estimated path is (1/s - 1 of the similarity),
- ATE mm: RMS position error after the rigid fit.

A scale error is the part of a side's drift no merge can see (it is common to both sides of a row): it
is what this benchmark is for. Each row is simulated at its scenario's camera rate.

    python benchmarks/front_end_scale.py --rows standard:10:0 handheld_walk:10:3 vehicle:10:7 \\
        --variant base --variant rough0:depth_rough_drop_fraction=0 [--workdir DIR] [--json out.json]

A variant is NAME[:KEY=VALUE,...] (odometry keys); `base` is the default configuration.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import yaml  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from orchard_mapping.config import load_config  # noqa: E402
from orchard_mapping.core.geometry import matrix_to_quat  # noqa: E402
from orchard_mapping.core.odometry import RGBDFrontEnd  # noqa: E402
from orchard_mapping.core.types import StampedTrajectory  # noqa: E402
from orchard_mapping.eval.ground_truth import GroundTruth, load_ground_truth  # noqa: E402
from orchard_mapping.eval.metrics import trajectory_error  # noqa: E402
from orchard_mapping.io.bags import read_rgbd  # noqa: E402
from orchard_mapping.io.results import portable_json
from orchard_mapping.sim.scenario import load_scenario  # noqa: E402
from orchard_mapping.sim.simulate import simulate  # noqa: E402


def parse_variant(text: str) -> tuple[str, dict]:
    name, _, sets = text.partition(":")
    over = {}
    for kv in filter(None, sets.split(",")):
        key, _, value = kv.partition("=")
        over[key.strip()] = yaml.safe_load(value)
    return name, over


def side_scale(sim: Path, gt: GroundTruth, side: str, overrides: dict) -> dict:
    """Front end alone on one side of a simulated row: scale %, ATE mm, keyframes, seconds."""
    cfg = load_config(overrides={"odometry": overrides} if overrides else None)
    seq = read_rgbd(sim / side, cfg.input.topics, mode="rgbd", max_pair_dt_s=cfg.input.max_pair_dt_s,
                    depth_min_m=cfg.input.depth_min_m, depth_max_m=cfg.input.depth_max_m)
    fe = RGBDFrontEnd(seq.intrinsics, cfg.odometry)
    t0 = time.perf_counter()
    for frame in seq:
        fe.track(frame)
    res = fe.result()
    seconds = time.perf_counter() - t0
    poses = np.array([k.T_odom_cam for k in res.keyframes])  # (K, 4, 4) odom_<side>
    est = StampedTrajectory(np.array([k.stamp for k in res.keyframes]), poses[:, :3, 3],
                            np.array([matrix_to_quat(T[:3, :3]) for T in poses]))
    true = gt.sides[side].trajectory
    rigid = trajectory_error(est, true)  # ATE after a rigid fit
    sim3 = trajectory_error(est, true, with_scale=True)  # true ~ s * est
    return {"keyframes": rigid.n_associated, "scale_pct": 100.0 * (1.0 / sim3.alignment_scale - 1.0),
            "ate_mm": rigid.ate_mm, "path_m": rigid.path_length_m, "seconds": seconds}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rows", nargs="+", default=["standard:10:0", "handheld_walk:10:3"],
                    help="SCENARIO:TREES:SEED")
    ap.add_argument("--variant", action="append", default=None, help="NAME[:KEY=VALUE,...]")
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "front_end_scale")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    variants = [parse_variant(v) for v in (args.variant or ["base", "rough0:depth_rough_drop_fraction=0"])]
    rows = []
    for spec in args.rows:
        scenario, trees, seed = spec.split(":")
        sim = args.workdir / f"{scenario}_{trees}trees_seed{seed}"
        if not (sim / "ground_truth.json").is_file():
            simulate(load_scenario(scenario, {"row.n_trees": int(trees)}), int(seed), sim, force=True)
        gt = load_ground_truth(sim / "ground_truth.json")
        for side in ("front", "back"):
            for name, over in variants:
                r = side_scale(sim, gt, side, over)
                rows.append({"row": spec, "side": side, "variant": name, **r})
                print(json.dumps(rows[-1]), flush=True)
    table = Table(title="front end alone: scale error and ATE per side")
    for col in ("row", "side", "variant", "keyframes", "scale %", "ATE mm", "s"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["row"], r["side"], r["variant"], str(r["keyframes"]), f"{r['scale_pct']:+.3f}",
                      f"{r['ate_mm']:.1f}", f"{r['seconds']:.0f}")
    for name, _ in variants:
        sel = [r for r in rows if r["variant"] == name]
        table.add_row("mean", "", name, "", f"|{np.mean([abs(r['scale_pct']) for r in sel]):.3f}|",
                      f"{np.mean([r['ate_mm'] for r in sel]):.1f}", "")
    Console().print(table)
    if args.json:
        args.json.write_text(portable_json(rows, indent=1))


if __name__ == "__main__":
    main()
