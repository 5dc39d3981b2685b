"""Peak memory does not grow with the row: only what a keyframe, a tree and the cloud keep (compact) does.

    .venv/bin/python benchmarks/memory_growth.py [--trees 4 8] [--seed 3] [--workdir DIR] [--json out.json]

One side of a 4-tree and of an 8-tree `single_pass` row (10 Hz, true trunk masks) is reconstructed (front end,
loop detection, windowed bundle adjustment, moving TSDF volume, trunk modelling) in a child process each, and
the child's peak resident memory while the side is processed (VmHWM, reset after start-up) is compared. Prints
a table; exits 1 when the longer row's peak is more than GROWTH_LIMIT_MB above the shorter's. ~2 minutes on
2 cores.

The windows are set small for these short rows (the defaults span ~12 m of row and 500 keyframes, longer than
an 8-tree row): keyframes cleaned 0.5 m behind the camera in 0.5 m batches (the volume then spans ~7.5 m:
3.2 m of reach either side of the cameras), BA windows of 80 keyframes.

What may grow with the row, per metre of one side (640x480, 10 Hz, ~17 keyframes per metre): keyframe
features (~0.6 MB), landmarks and observations (~0.3 MB), the fused cloud (~40 k points, ~0.6 MB, with a
few float64 copies while trunks are modelled) and cropped trunk views (~0.7 MB): ~4 MB per metre, ~40 MB
for the 9.2 m the 8-tree row adds. Measured: +18 to +25 MB; the code before the streaming core (one volume for
the whole side, whole-frame views, one global BA): +257 MB.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from rich.console import Console
from rich.table import Table

from orchard_mapping.io.results import portable_json
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import simulate

# MB the 8-tree row may add to the 4-tree row's peak: the ~40 MB of compact growth above, doubled for the
# allocator's own slack (glibc keeps freed blocks; the peak may land in another stage on another machine).
GROWTH_LIMIT_MB = 80.0

SMALL_WINDOWS = {"fusion": {"clean_after_m": 0.5, "clean_batch_m": 0.5},
                 "ba": {"window": 80, "window_tail": 25, "window_hold": 10}}

_CHILD = """
import json, re, sys
from orchard_mapping.config import load_config
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.pipeline import Timings, reconstruct_side

def hwm_mb():
    return int(re.search(r"VmHWM:\\s+(\\d+) kB", open("/proc/self/status").read()).group(1)) / 1024

cfg = load_config(overrides=json.loads(sys.argv[2]))
seq = read_rgbd(sys.argv[1])
start = hwm_mb()
with open("/proc/self/clear_refs", "w") as f:  # Linux: the peak (VmHWM) starts again from the current RSS
    f.write("5")
sm = reconstruct_side(seq, "front", cfg, Timings())
print(json.dumps({"peak_mb": hwm_mb(), "start_mb": start,
                  "keyframes": len(sm.keyframe_stamps), "trunks": len(sm.trunks), "points": len(sm.cloud_points)}))
"""


def side_peak(bag: Path, masks: Path) -> dict:
    """One side reconstructed in a child process: its peak and start-up RSS (MB), keyframes, trunks, points."""
    overrides = {**SMALL_WINDOWS, "trunks": {"source": "masks", "masks_dir": str(masks)}}
    # The child starts as `orchard-map` does from a shell: without what this process's imports put into its
    # environment (open3d sets TCM_ENABLE, the ROS and OpenCV wheels extend LD_LIBRARY_PATH). Inherited,
    # they changed the child's thread pools and its peak by 85-145 MB from run to run (measured).
    env = {k: v for k, v in os.environ.items() if k not in ("TCM_ENABLE", "LD_LIBRARY_PATH")}
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    out = subprocess.run([sys.executable, "-c", _CHILD, str(bag), json.dumps(overrides)], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", type=int, nargs=2, default=[4, 8], metavar=("SHORT", "LONG"))
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--workdir", type=Path, default=None, help="keep the simulated rows here (default: removed)")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = a.workdir or Path(tmp)
        for n in a.trees:
            sc = load_scenario("single_pass", {"row.n_trees": n, "camera.rate_hz": 10, "masks_every": 1})
            sim = simulate(sc, a.seed, root / f"mem{n}", record=("front",)).out_dir
            rows[n] = side_peak(sim / "front", sim / "masks")
    short, long_ = (rows[n] for n in a.trees)
    growth = long_["peak_mb"] - short["peak_mb"]
    table = Table(title=f"peak RSS of one side, {a.trees[0]} vs {a.trees[1]} trees (limit +{GROWTH_LIMIT_MB:.0f} MB)")
    for col in ("trees", "keyframes", "points", "trunks", "start-up MB", "peak MB"):
        table.add_column(col, justify="right")
    for n, r in rows.items():
        table.add_row(str(n), str(r["keyframes"]), str(r["points"]), str(r["trunks"]), f"{r['start_mb']:.0f}",
                      f"{r['peak_mb']:.0f}")
    Console().print(table)
    print(f"growth: {growth:+.1f} MB")
    if a.json:
        a.json.write_text(portable_json({"rows": rows, "growth_mb": growth, "limit_mb": GROWTH_LIMIT_MB}))
    # the rows were reconstructed with their trees, and the longer one holds more
    ok = long_["trunks"] >= a.trees[1] - 1 and short["trunks"] >= a.trees[0] - 1 and \
        long_["keyframes"] > 1.5 * short["keyframes"] and growth <= GROWTH_LIMIT_MB
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
