"""Peak memory does not grow with the row: only what a keyframe, a tree and the cloud keep (compact) does.

One side of a 2-tree and of a 5-tree row is reconstructed (front end, loop detection, windowed bundle
adjustment, moving TSDF volume, trunk detection and modelling) in a child process each, and the child's
peak resident memory (ru_maxrss) is compared. The windows are set small for these short rows (the
defaults span ~12 m of row and 300 keyframes, longer than a 5-tree row): a volume reaching 1.7 m from the
cameras, keyframes cleaned 0.5 m behind the camera, BA windows of 80 keyframes.

What may grow with the row, measured per metre of one side (640x480, 10 Hz, ~23 keyframes per metre):
keyframe features (~0.8 MB), landmark observations (~0.3 MB), the fused cloud (~0.6 MB, a few float64
copies of it while trunks are modelled: ~2 MB) and cropped trunk views (~0.4 MB): ~4 MB per metre, ~30 MB
for the 7 m the 5-tree row adds. A volume of the whole row would add ~12 MB per metre at 1.5 m depth
(~85 MB), whole-frame views ~1.2 MB per view (7 per metre: ~60 MB), a global BA ~1 MB per keyframe.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import simulate

# MB the 5-tree row may add to the 2-tree row's peak: the ~30 MB of compact growth above, doubled for the
# allocator's own slack (glibc keeps freed blocks; the peak lands in a different stage on another machine).
GROWTH_LIMIT_MB = 60.0

SMALL_WINDOWS = {"fusion": {"depth_max_m": 1.5, "clean_after_m": 0.5, "clean_batch_m": 0.5},
                 "ba": {"window": 80, "window_tail": 25, "window_hold": 10}}

_CHILD = """
import json, resource, sys
from orchard_mapping.config import load_config
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.pipeline import Timings, reconstruct_side
cfg = load_config(overrides=json.loads(sys.argv[2]))
sm = reconstruct_side(read_rgbd(sys.argv[1]), "front", cfg, Timings())
print(json.dumps({"peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "keyframes": len(sm.keyframe_stamps), "trunks": len(sm.trunks), "points": len(sm.cloud_points)}))
"""


def _peak(bag: Path, masks: Path) -> dict:
    overrides = {**SMALL_WINDOWS, "trunks": {"source": "masks", "masks_dir": str(masks)}}
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    out = subprocess.run([sys.executable, "-c", _CHILD, str(bag), json.dumps(overrides)], env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def rows(tmp_path_factory) -> dict[int, dict]:
    out = {}
    for n in (2, 5):
        sc = load_scenario("single_pass", {"row.n_trees": n, "camera.rate_hz": 10, "masks_every": 1})
        sim = simulate(sc, 3, tmp_path_factory.mktemp(f"mem{n}") / "sim", record=("front",)).out_dir
        out[n] = _peak(sim / "front", sim / "masks")
    return out


def test_peak_memory_does_not_grow_with_the_row(rows, accuracy):
    small, large = rows[2], rows[5]
    print(f"\npeak RSS: 2 trees {small['peak_mb']:.0f} MB ({small['keyframes']} keyframes, {small['points']} points), "
          f"5 trees {large['peak_mb']:.0f} MB ({large['keyframes']} keyframes, {large['points']} points)")
    assert large["trunks"] >= 4 and small["trunks"] >= 1  # the rows were reconstructed with their trees
    assert large["keyframes"] > 2 * small["keyframes"]
    accuracy.at_most("peak RSS growth from a 2-tree to a 5-tree side, MB", large["peak_mb"] - small["peak_mb"],
                     GROWTH_LIMIT_MB)
