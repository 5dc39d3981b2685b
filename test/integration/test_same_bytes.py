"""Same recording, same bytes: `orchard-map run` twice on one small row, on one and on two threads
(OMP_NUM_THREADS and OPENBLAS_NUM_THREADS: Open3D's OpenMP loops, numpy's and scipy's OpenBLAS), writes the
same result folder: every file byte for byte (the PNG figures by their pixels), but timings.json, which is the
run's wall clock (docs/results.md, "Same recording, same bytes").

The row: the `standard` scenario, 2 trees, both sides, at 320x240 and 5 Hz (enough to find both trunks on
each side and merge), with the fruit stage on so that fruit.csv is written too. The two runs go side by side:
on 2 cores the test takes 1-2 minutes.
"""

from __future__ import annotations

import datetime
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import simulate

# `make test-slow` (and CI): two runs of a row on one and two threads, ~1.5 minutes
pytestmark = pytest.mark.slow

SMALL_CAMERA = {"camera.width": 320, "camera.height": 240, "camera.fx": 307.5, "camera.fy": 307.5,
                "camera.cx": 159.5, "camera.cy": 119.5, "camera.rate_hz": 5, "masks_every": 0}
WALL_CLOCK = {"timings.json"}  # the one file that records how long the run took
# what a merged run with the fruit stage writes: the comparison must not pass on a run that stopped short
EXPECTED = {"trajectory_front.tum", "trajectory_back.tum", "odometry_front.tum", "odometry_back.tum", "front.ply",
            "back.ply", "trunks.json", "grounds.json", "side_merge.json", "trajectory_front_map.tum",
            "trajectory_back_map.tum", "merged.ply", "row.png", "trees.json", "trees.csv", "trees.laz", "fruit.csv",
            "config.effective.yaml", "timings.json"}


@pytest.fixture(scope="module")
def row(scratch) -> Iterator[Path]:
    with scratch("same_bytes") as root:
        yield simulate(load_scenario("standard", {"row.n_trees": 2, **SMALL_CAMERA}), 3, root / "sim").out_dir


def _start_run(sim: Path, out: Path, threads: int) -> subprocess.Popen:
    """`orchard-map run` in a child process with `threads` OpenMP and OpenBLAS threads (both are read once, as
    the libraries load: only a fresh process can change them)."""
    # started as from a shell: without what this process's imports put into its environment (benchmarks/memory_growth.py)
    env = {k: v for k, v in os.environ.items() if k not in ("TCM_ENABLE", "LD_LIBRARY_PATH")}
    env.update(ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", OMP_NUM_THREADS=str(threads),
               OPENBLAS_NUM_THREADS=str(threads))
    return subprocess.Popen([sys.executable, "-m", "orchard_mapping.cli.main", "run", str(sim / "front"),
                             str(sim / "back"), "--out", str(out), "--set", "fruit.enabled=true"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file()}


def test_one_row_gives_the_same_files_on_one_and_two_threads(row, tmp_path):
    outs = {n: tmp_path / f"threads{n}" for n in (1, 2)}
    runs = {n: _start_run(row, out, n) for n, out in outs.items()}  # side by side: half the wall time on 2 cores
    for n, p in runs.items():
        log, _ = p.communicate(timeout=600)
        assert p.returncode == 0, f"OMP_NUM_THREADS={n}:\n{log[-3000:]}"
    names = _files(outs[1])
    assert names == _files(outs[2])
    assert EXPECTED <= names and any(n.startswith("trees/") and n.endswith(".png") for n in names), sorted(names)
    differ = []
    for name in sorted(names - WALL_CLOCK):
        a, b = (outs[n] / name for n in (1, 2))
        if name.endswith(".png"):  # by pixels: a PNG's metadata is no result
            same = np.array_equal(cv2.imread(str(a), cv2.IMREAD_UNCHANGED), cv2.imread(str(b), cv2.IMREAD_UNCHANGED))
        else:
            same = a.read_bytes() == b.read_bytes()
        if not same:
            differ.append(name)
    assert not differ, f"differ between 1 and 2 threads: {differ}"

    # and on another day: trees.laz's header carries the recording's day (UTC), not the day it was written
    import laspy

    first = float(read_rgbd(row / "front").stamps[0])
    assert laspy.read(str(outs[1] / "trees.laz")).header.creation_date == (
        datetime.datetime.fromtimestamp(first, datetime.timezone.utc).date())
