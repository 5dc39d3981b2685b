"""Benchmark: the node graph on a replayed row, as on the vehicle (`orchard-map launch --bag ... --record`).

For each replay rate: the player replays both sides of a simulated `standard` row into the graph (each
node its own process, loopback DDS); the recorder keeps the odometry node's status, from which the table
shows, per rate: colour images sent (counted in the bags), received by the odometry node, lost (sent -
received), the losses the node reported (against the player's count after each bag; of them, those it saw
by itself as gaps in the camera's rhythm), frames tracked, the time from
each side's end to its side map, the time from the second side's end (the player's `end` on the side
topic, as the recorder received it) to the trees published by the trait reporter (as the recorder
received them) with the side merger's own seconds, and the whole replay's wall time.

Usage:
  python benchmarks/live.py [--trees 2] [--rates 1 2] [--seed 0] [--workdir /tmp/live_bench] [--sim DIR]
        [--masks] [--repeat 1] [--json out.json]
--repeat N replays each rate N times and adds a row of medians (the JSON keeps every run, with each side's
finishing stages in seconds).
--masks takes trunks from the simulator's masks (trunks.source=masks) instead of the shipped detector.
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

import numpy as np
import yaml
from rich.console import Console
from rich.table import Table

from orchard_mapping.io.bags import iter_messages, iter_raw
from orchard_mapping.io.results import portable_json
from orchard_mapping.resources import config_dir
from scale import simulate_row  # benchmarks/scale.py, beside this file

COLOUR = "/camera/color/image_raw"


def replay(sim: Path, rate: float, work: Path, masks: bool) -> dict:
    rec = work / f"recorded_{rate:g}x"
    params = yaml.safe_load((config_dir() / "ros_params.yaml").read_text())
    if masks:
        params["/**"]["ros__parameters"]["trunks"].update(source="masks", masks_dir=str(sim / "masks"))
    pfile = work / "params.yaml"
    pfile.write_text(yaml.safe_dump(params))
    if rec.exists():
        subprocess.run(["rm", "-rf", str(rec)], check=True)
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    t0 = time.perf_counter()
    with (work / f"launch_{rate:g}x.log").open("w") as log:
        rc = subprocess.run([sys.executable, "-m", "orchard_mapping.cli.main", "launch", "--bag", str(sim / "front"),
                             "--bag", str(sim / "back"), "--rate", str(rate), "--record", str(rec),
                             "--params", str(pfile), "--out", str(work / f"result_{rate:g}x")], env=env, stdout=log, stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - t0
    if rc != 0:
        raise SystemExit(f"{rate:g}x: orchard-map launch exited {rc} (log {work}/launch_{rate:g}x.log)")
    status = [json.loads(m.data) for _, m in iter_messages(rec, "/orchard/odometry/status")][-1]
    side_end = [t for t, m in iter_messages(rec, "/orchard/side") if m.data == "end"]
    trees = [t for t, _ in iter_messages(rec, "/orchard/trees")]
    merger = [json.loads(m.data) for _, m in iter_messages(rec, "/orchard/side_merger/status")][-1]
    stamps = {side: [m.log_time_ns for m in iter_raw(sim / side, [COLOUR])] for side in ("front", "back")}
    sent = sum(len(t) for t in stamps.values())
    duration = sum((t[-1] - t[0]) / 1e9 for t in stamps.values())
    return {"rate": rate, "sent": sent, "received": status["colour"], "lost": sent - status["colour"],
            "lost_reported": status["lost_vs_player"], "gaps_seen": status["missed"],
            "tracked": sum(status["processed"].values()),
            "side_map_latency_s": status["side_map_latency_s"], "recording_s": duration, "wall_s": wall,
            "second_end_to_trees_s": trees[-1] - side_end[-1] if trees and side_end else None,
            "merge_s": merger["seconds"][-1] if merger["seconds"] else None,
            "finish_stages_s": status.get("finish_stages_s", {}), "errors": status["errors"]}


def _f(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.1f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trees", type=int, default=2)
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "live_bench")
    ap.add_argument("--sim", type=Path, help="reuse a simulated row (folder with front/, back/)")
    ap.add_argument("--masks", action="store_true")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    args.workdir.mkdir(parents=True, exist_ok=True)
    sim = args.sim or simulate_row(args.trees, 15.0, args.seed,
                                   args.workdir / f"standard_{args.trees}trees_seed{args.seed}",
                                   ["masks_every=1"] if args.masks else [])
    rows = [replay(sim, r, args.workdir, args.masks) for r in args.rates for _ in range(args.repeat)]
    t = Table(title=f"node graph on a replayed {sim.name} row (orchard-map launch), 2 cores")
    for col in ("rate", "colour sent", "received", "lost", "lost, reported by node", "of which gaps seen", "tracked",
                "side end -> map front s", "side end -> map back s", "2nd side end -> trees s", "merge s",
                "recording s", "wall s"):
        t.add_column(col, justify="right")
    for r in rows:
        lat = r["side_map_latency_s"]
        t.add_row(f"{r['rate']:g}x", str(r["sent"]), str(r["received"]), str(r["lost"]),
                  str(r["lost_reported"]), str(r["gaps_seen"]), str(r["tracked"]), f"{lat.get('front', float('nan')):.1f}",
                  f"{lat.get('back', float('nan')):.1f}", _f(r["second_end_to_trees_s"]), _f(r["merge_s"]),
                  f"{r['recording_s']:.1f}", f"{r['wall_s']:.1f}")
    if args.repeat > 1:
        for rate in args.rates:
            runs = [r for r in rows if r["rate"] == rate]

            def med(get, runs=runs) -> str:
                vals = [v for v in (get(r) for r in runs) if v is not None]
                return f"{float(np.median(vals)):.1f}" if vals else "n/a"
            t.add_row(f"{rate:g}x median of {len(runs)}", "", "", med(lambda r: r["lost"]), "", "", "",
                      med(lambda r: r["side_map_latency_s"].get("front")),
                      med(lambda r: r["side_map_latency_s"].get("back")), med(lambda r: r["second_end_to_trees_s"]),
                      med(lambda r: r["merge_s"]), "", med(lambda r: r["wall_s"]))
    Console(width=200).print(t)
    if args.json:
        args.json.write_text(portable_json(rows, indent=1))


if __name__ == "__main__":
    main()
