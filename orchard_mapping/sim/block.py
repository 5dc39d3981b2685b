"""Simulate one drive along a whole block of rows (path mode `block`): one bag, the truth per row and for the block.

Output folder (docs/ground_truth.md):
  OUT/block/                  the drive, one rosbag2 (MCAP) bag, no side topic: `orchard-map run` tells the rows
                              and sides from the camera's turns
  OUT/row_<k>/ground_truth.json   row k's truth in the single-row schema: its trees, and each side's path as the
                              simulator labels the drive (half of each turn to the pass before it, half to the
                              next), in an odom frame at that pass's first frame
  OUT/ground_truth.json       the block (BLOCK_TRUTH_SCHEMA): its rows, their trees, the whole drive in world
  OUT/tree_surfaces.npz       every tree's surface samples (linked into each row_<k>/ for the evaluator)
  OUT/masks/block/*.png       instance masks every `masks_every` frames (global tree ids)

The simulator's cut of a turn and the product's (core.sides, half way round by the tracked heading) may fall a
frame apart; eval.block re-anchors each row's truth at the frames the result's sides begin with, from the drive
in world kept here.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from orchard_mapping.config import TopicsConfig
from orchard_mapping.io.block import row_folder
from orchard_mapping.io.results import atomic_write_text
from orchard_mapping.sim.scenario import Scenario
from orchard_mapping.sim.simulate import (
    T0_FRONT,
    Progress,
    Rig,
    SimulationResult,
    _mask_dir,
    _record,
    truth_document,
)
from orchard_mapping.sim.trajectory import CameraPath, block_path
from orchard_mapping.sim.truth import TREE_SURFACES_NPZ, VisibilityAccumulator, write_tree_surfaces

log = logging.getLogger(__name__)

BLOCK_TRUTH_SCHEMA = "orchard_mapping.block_ground_truth/1"
BLOCK_BAG = "block"
SIDES = ("front", "back")


def _pass(drive: CameraPath, mask: np.ndarray) -> CameraPath:
    pos = drive.poses[mask, :3, 3]
    return CameraPath(drive.stamps[mask], drive.poses[mask], drive.sides[mask],
                      float(np.sum(np.linalg.norm(np.diff(pos, axis=0), axis=1))))


def _world_tum(path: CameraPath) -> list[list[float]]:
    q = Rotation.from_matrix(path.poses[:, :3, :3]).as_quat()  # x y z w
    return [[round(float(s), 6), *map(float, p), *map(float, qq)]
            for s, p, qq in zip(path.stamps, path.poses[:, :3, 3], q, strict=True)]


def _link(src: Path, dst: Path) -> None:
    """dst as a hard link to src (a copy where the file system has none)."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copyfile(src, dst)


def simulate_block(sc: Scenario, seed: int, out: Path, *, topics: TopicsConfig = TopicsConfig(),
                   progress: Progress | None = None, compress: bool = False) -> SimulationResult:
    """Render the block drive of scenario `sc` (path.mode block) into `out` (an empty folder)."""
    rig = Rig.build(sc, seed)
    scene = rig.scene
    dh = sc.trunk.diameter_height_m
    drive = block_path(sc, scene.rows, scene.terrain, np.random.default_rng([seed, 1]), T0_FRONT)
    assert drive.rows is not None
    keys = np.array([f"{r}/{s}" for r, s in zip(drive.rows, drive.sides, strict=True)])
    acc = {k: VisibilityAccumulator(scene, rig.intrinsics, dh) for k in sorted(set(keys))}
    _record(scene, rig.renderer, rig.sensor, drive, out / BLOCK_BAG, _mask_dir(out, BLOCK_BAG, sc), sc.masks_every,
            np.random.default_rng([seed, 2]), acc, topics, BLOCK_BAG, progress, with_side_topic=False,
            compress=compress, acc_keys=keys)
    write_tree_surfaces(scene, out / TREE_SURFACES_NPZ)

    rows = []
    for line in scene.rows:
        folder = out / row_folder(line.number)
        folder.mkdir()
        paths = {side: _pass(drive, (drive.rows == line.number) & (drive.sides == side)) for side in SIDES}
        T_world_odom = {side: paths[side].poses[0] for side in SIDES}
        row_acc = {side: acc[f"{line.number}/{side}"] for side in SIDES}
        doc = truth_document(sc, seed, scene, row_acc, paths, T_world_odom, dict.fromkeys(SIDES, BLOCK_BAG),
                             dict.fromkeys(SIDES, True), line.tree_ids)
        doc["row"] = line.number
        _link(out / TREE_SURFACES_NPZ, folder / TREE_SURFACES_NPZ)
        atomic_write_text(folder / "ground_truth.json", json.dumps(doc, indent=1))
        rows.append({"row": line.number, "y_m": line.y, "x_m": list(line.x), "tree_ids": list(line.tree_ids),
                     "truth": f"{row_folder(line.number)}/ground_truth.json",
                     "passes": {side: {"first_stamp": float(paths[side].stamps[0]),
                                       "last_stamp": float(paths[side].stamps[-1]),
                                       "frames": len(paths[side].stamps)} for side in SIDES}})
    truth = {
        "schema": BLOCK_TRUTH_SCHEMA,
        "scenario": sc.name,
        "seed": seed,
        "n_rows": len(scene.rows),
        "n_trees": len(scene.trees),
        "row_spacing_m": sc.block.row_spacing_m,
        "rows": rows,
        # the whole drive, camera optical frame in world, every frame: each row's truth is re-anchored from it
        # at the frames the result's sides begin with (eval.block)
        "drive": {"bag": BLOCK_BAG, "frames": len(drive.stamps), "path_length_m": round(drive.path_length_m, 4),
                  "rows": drive.rows.tolist(), "sides": drive.sides.tolist(), "trajectory": _world_tum(drive)},
        "scenario_config": sc.model_dump(mode="json"),
    }
    truth_path = out / "ground_truth.json"
    atomic_write_text(truth_path, json.dumps(truth, indent=1))  # last: its presence means "complete"
    log.info("simulated block %s: %d rows, %d frames", out, len(scene.rows), len(drive.stamps))
    return SimulationResult(out, {BLOCK_BAG: out / BLOCK_BAG}, truth_path, {BLOCK_BAG: len(drive.stamps)})
