"""Shared simulator fixtures: a few small, seeded recordings written once per session.

The machine running the suite is small and shared, so every recording here is
as cheap as it can be while still exercising the real pipeline (scene ->
renderer -> sensor model -> bag -> ground truth): a 3-tree row, the camera at
half resolution (320x240, same field of view as 640x480) and 2 Hz, walked at
1 m/s. Most tests reuse `standard_sim`; the determinism and loop tests use
their own even smaller rows.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orchard_mapping.core.types import RGBDFrame
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.sim.scenario import Scenario, load_scenario
from orchard_mapping.sim.scene import Scene, build_scene
from orchard_mapping.sim.simulate import SimulationResult, simulate

# Half-resolution camera with the default 640x480 camera's field of view (fx scales with width).
HALF_RES: dict[str, Any] = {
    "camera.width": 320, "camera.height": 240,
    "camera.fx": 307.5, "camera.fy": 307.5, "camera.cx": 159.5, "camera.cy": 119.5,
}
# Quarter resolution for tests that only compare runs with each other.
QUARTER_RES: dict[str, Any] = {
    "camera.width": 160, "camera.height": 120,
    "camera.fx": 153.75, "camera.fy": 153.75, "camera.cx": 79.5, "camera.cy": 59.5,
}
# Cheap rows for tests that compare runs: few leaves and fruit make the canopy-volume alpha complex fast.
TINY_ROW: dict[str, Any] = {
    "row.n_trees": 2, "camera.rate_hz": 1.0, "path.speed_mps": 1.0,
    "canopy.leaves_per_m3": 1500.0, "fruit.per_tree": [3, 5], "masks_every": 2, **QUARTER_RES,
}

STANDARD_SEED = 7
STANDARD_OVERRIDES: dict[str, Any] = {
    "row.n_trees": 3, "camera.rate_hz": 2.0, "path.speed_mps": 1.0, "masks_every": 1, **HALF_RES,
}


def pose_matrix(row: list[float] | np.ndarray) -> np.ndarray:
    """4x4 pose from a TUM row [t, tx, ty, tz, qx, qy, qz, qw]."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(np.asarray(row[4:8], float)).as_matrix()
    T[:3, 3] = row[1:4]
    return T


@dataclass
class SimRun:
    """One simulated recording, with its truth and the scene rebuilt from the same scenario and seed."""

    scenario: Scenario
    seed: int
    result: SimulationResult
    truth: dict
    scene: Scene
    _frames: dict[str, list[RGBDFrame]]

    @property
    def out(self) -> Path:
        return self.result.out_dir

    def frames(self, bag: str) -> list[RGBDFrame]:
        """Decoded frames of bag `bag` ("front", "back" or "loop"), read back from disk once."""
        if bag not in self._frames:
            self._frames[bag] = list(read_rgbd(self.result.bags[bag]))
        return self._frames[bag]

    def world_poses(self, side: str) -> tuple[np.ndarray, np.ndarray]:
        """Truth trajectory of a side: stamps (N,) s and T_world_cam (N, 4, 4)."""
        s = self.truth["sides"][side]
        T_world_odom = np.asarray(s["T_world_odom"])
        traj = np.asarray(s["trajectory"])
        return traj[:, 0], np.stack([T_world_odom @ pose_matrix(r) for r in traj])

    def masks(self, side: str) -> list[tuple[int, float, np.ndarray]]:
        """(frame index, stamp, (H, W) uint16 mask) for every mask written for `side`."""
        d = self.out / "masks" / side
        rows = (d / "index.csv").read_text().split()[1:]
        out = []
        for r in rows:
            i, stamp = r.split(",")
            m = cv2.imread(str(d / f"{int(i):06d}.png"), cv2.IMREAD_UNCHANGED)
            assert m is not None and m.dtype == np.uint16
            out.append((int(i), float(stamp), m))
        return out


def run_sim(tmp: Path, name: str, overrides: dict[str, Any], seed: int) -> SimRun:
    sc = load_scenario(name, overrides)
    res = simulate(sc, seed, tmp)
    truth = json.loads(res.truth_path.read_text())
    return SimRun(sc, seed, res, truth, build_scene(sc, seed), {})


@pytest.fixture(scope="session")
def standard_sim(tmp_path_factory: pytest.TempPathFactory) -> SimRun:
    """The standard scenario (two_sweep per side), 3 trees, masks every frame."""
    return run_sim(tmp_path_factory.mktemp("sim") / "standard", "standard", STANDARD_OVERRIDES, STANDARD_SEED)


@pytest.fixture(scope="session")
def tiny_single_pass(tmp_path_factory: pytest.TempPathFactory) -> SimRun:
    """A 2-tree single_pass row at quarter resolution (determinism and single-pass checks)."""
    return run_sim(tmp_path_factory.mktemp("sim") / "tiny_a", "standard",
                   {**TINY_ROW, "path.mode": "single_pass"}, seed=3)


@pytest.fixture(scope="session")
def make_sim(tmp_path_factory: pytest.TempPathFactory):
    """Factory: make_sim(scenario name, overrides, seed) -> SimRun written into a fresh temporary folder."""

    def make(name: str, overrides: dict[str, Any], seed: int) -> SimRun:
        return run_sim(tmp_path_factory.mktemp("sim") / name, name, overrides, seed)

    return make


@pytest.fixture(scope="session")
def tiny_row() -> dict[str, Any]:
    """Overrides for a cheap 2-tree row at quarter resolution and 1 Hz."""
    return dict(TINY_ROW)


@pytest.fixture(scope="session")
def half_res() -> dict[str, Any]:
    """Overrides for a 320x240 camera with the default camera's field of view."""
    return dict(HALF_RES)
