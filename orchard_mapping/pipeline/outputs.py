"""What the pipeline writes into the result folder (docs/results.md): each side's trajectories and cloud, the
trunks and grounds, and the merge's outputs."""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from orchard_mapping.config import OrchardConfig
from orchard_mapping.core.geometry import matrix_to_quat, move_with_keyframes
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.io.bags import RGBDSequence
from orchard_mapping.io.figures import RowView, write_row_png, write_tree_png
from orchard_mapping.io.landmarks import GROUNDS_JSON, TRUNKS_JSON, write_grounds, write_trunks
from orchard_mapping.io.laz import TREES_LAZ, write_laz
from orchard_mapping.io.results import (
    SIDE_MERGE_JSON,
    TREES_CSV,
    TREES_JSON,
    ResultTree,
    atomic_write_json,
    atomic_write_text,
    map_trajectory_filename,
    write_side_merge,
    write_tum,
)
from orchard_mapping.pipeline.fruit import TreeFruit
from orchard_mapping.pipeline.merge import MergeOutcome, clouds_in_map, map_poses
from orchard_mapping.pipeline.traits import RowLabels

# What a merge writes into the result folder (docs/results.md).
MERGED_PLY, ROW_PNG, TREE_FIGURES, FRUIT_CSV = "merged.ply", "row.png", "trees", "fruit.csv"
INPUTS_JSON = "inputs.json"  # the bags read and what was wrong with them
INPUTS_SCHEMA = "orchard_mapping.inputs/1"


MERGE_OUTPUTS = (SIDE_MERGE_JSON, TREES_JSON, TREES_CSV, map_trajectory_filename("*"), MERGED_PLY, ROW_PNG,
                 TREES_LAZ, TREE_FIGURES, FRUIT_CSV)
# Everything `orchard-map run` may write (glob patterns): a second run into the folder replaces the whole set
# (io.results.staged_folder), so that no file of the earlier run stays beside the new ones as if it were theirs.
RUN_OUTPUTS = (*MERGE_OUTPUTS, "trajectory_*.tum", "odometry_*.tum", "front.ply", "back.ply", TRUNKS_JSON,
               GROUNDS_JSON, "timings.json", "config.effective.yaml", INPUTS_JSON)


def write_cloud(path: Path, points: np.ndarray, colors: np.ndarray) -> None:
    """PLY (binary), written atomically."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    pc.colors = o3d.utility.Vector3dVector(colors.astype(np.float64) / 255.0)
    _write_ply_atomically(path, lambda tmp: o3d.io.write_point_cloud(tmp, pc, write_ascii=False))


def _write_ply_atomically(path: Path, write: Callable[[str], bool]) -> None:
    """write(tmp) -> success into a temporary file beside `path`, then renamed onto it."""
    tmp = path.with_name(f".{path.stem}.partial.ply")
    if not write(str(tmp)):
        tmp.unlink(missing_ok=True)
        # Open3D says only that it failed (a full disk too): the file named, io.results.staged_folder can tell
        # the user which folder could not take it
        raise OSError(None, "could not write the point cloud", str(path))
    os.replace(tmp, path)


def write_labelled_cloud(path: Path, points: np.ndarray, colors: np.ndarray, side: np.ndarray) -> None:
    """PLY (binary) with colour and a per-point `side` label (uchar: 0 front, 1 back), written atomically."""
    import open3d as o3d

    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(np.ascontiguousarray(points, np.float32))
    pc.point.colors = o3d.core.Tensor(np.ascontiguousarray(colors, np.uint8))
    pc.point.side = o3d.core.Tensor(np.ascontiguousarray(side, np.uint8).reshape(-1, 1))
    _write_ply_atomically(path, lambda tmp: o3d.t.io.write_point_cloud(tmp, pc, write_ascii=False))


def _trajectory(stamps: np.ndarray, poses: np.ndarray, frame_id: str) -> StampedTrajectory:
    q = np.array([matrix_to_quat(T[:3, :3]) for T in poses])
    return StampedTrajectory(stamps, poses[:, :3, 3], q, frame_id)


def write_inputs(out: Path, seqs: dict[str, RGBDSequence]) -> None:
    """inputs.json: each bag read (by the keys open_sides gave it: its sides, or "drive"), its frames, and what
    read_rgbd found wrong with it and worked round (io.bags.InputNotes), so that a result made of a recording
    cut short or with a gap says so after the run's warnings have scrolled away (docs/results.md)."""
    bags: dict[str, dict] = {}
    for key, seq in seqs.items():
        if seq.bag in bags:  # one bag holding both sides
            bags[seq.bag]["sides"].append(key)
            continue
        n = seq.notes
        cut = None
        if n.cut_short is not None:
            c = n.cut_short
            cut = {"messages_kept": c.messages, "last_log_time_s": (c.last_log_time_ns or 0) / 1e9,
                   "messages_lost": c.lost_messages}
        bags[seq.bag] = {"bag": seq.bag, "sides": [key], "frames": len(seq), "flags": list(n.flags),
                         "colour_without_depth": n.colour_without_depth, "duplicate_stamps": n.duplicate_stamps,
                         "out_of_order_stamps": n.out_of_order_stamps, "gaps_s": [list(g) for g in n.gaps],
                         "cut_short": cut}
    flags = sorted({f for b in bags.values() for f in b["flags"]})
    atomic_write_json(out / INPUTS_JSON, {"schema": INPUTS_SCHEMA, "flags": flags, "bags": list(bags.values())})


def write_side(out: Path, sm: SideMap) -> None:
    write_tum(out / f"trajectory_{sm.side}.tum", _trajectory(sm.keyframe_stamps, sm.keyframe_poses, sm.frame_id))
    # The front end's keyframe poses before loop closure and BA: what the back end improved on.
    write_tum(out / f"odometry_{sm.side}.tum", _trajectory(sm.keyframe_stamps, sm.odometry_poses, sm.frame_id))
    if len(sm.cloud_points):
        write_cloud(out / f"{sm.side}.ply", sm.cloud_points, sm.cloud_colors)


def write_landmarks(out: Path, sides: dict[str, SideMap], cfg: OrchardConfig) -> None:
    """trunks.json and grounds.json of every side (docs/results.md)."""
    by_side = {s: (sm.frame_id, sm.trunks) for s, sm in sides.items()}
    write_trunks(out / TRUNKS_JSON, by_side, cfg.trunks.diameter_height_m)
    write_grounds(out / GROUNDS_JSON, by_side)


def write_merge(out: Path, m: MergeOutcome, sides: dict[str, SideMap],
                clouds: dict[str, np.ndarray] | None = None, trees: list[ResultTree] | None = None) -> None:
    """side_merge.json, both sides' trajectories in map (= odom_front), merged.ply and row.png (with `trees`,
    each tree's id, height and volume above it)."""
    al, it, sba = m.alignment, m.initial, m.sba
    extra: dict = {}
    if sba is not None:
        pair_ids = list(m.pairs)
        extra["semantic_ba"] = {
            "trunk_axis_gap_mm": {"before": {"median": float(np.median(list(sba.gaps_before_mm.values()))),
                                             "max": float(max(sba.gaps_before_mm.values()))},
                                  "after": {"median": float(np.median(list(sba.gaps_after_mm.values()))),
                                            "max": float(max(sba.gaps_after_mm.values()))},
                                  "per_pair": [{"front_id": pair_ids[k][0], "back_id": pair_ids[k][1],
                                                "before": sba.gaps_before_mm[k], "after": sba.gaps_after_mm[k]}
                                               for k in sorted(sba.gaps_after_mm)]},
            "error_initial": sba.error_initial, "error_final": sba.error_final, "iterations": sba.iterations}
    residuals: dict = {}
    if it is not None and al is not None:
        residuals = {"pairs": [asdict(r) for r in it.residuals], "huber_cost_initial": it.cost_initial,
                     "huber_cost_final": it.cost_final, "boundary_rms_m": al.boundary_rms_m}
    overlap = {"trunks_front": len(sides["front"].trunks), "trunks_back": len(sides["back"].trunks),
               "pairs": len(m.pairs)}
    if al is not None:  # "trunk_pairs", or "trunk_lines" where the alignment fell back (alignment.fallback)
        extra["alignment_method"] = al.method
    if al is not None:
        overlap["x_range_m"] = list(al.overlap_m)
    write_side_merge(out / SIDE_MERGE_JSON, m.T_front_back, method=m.method, residuals=residuals,
                     overlap=overlap, alignment_log=al.log if al is not None else [], **extra)
    poses = map_poses(m, sides)
    for side, P in poses.items():  # (K, 4, 4) T_map_cam
        write_tum(out / map_trajectory_filename(side), StampedTrajectory(
            sides[side].keyframe_stamps, P[:, :3, 3], np.array([matrix_to_quat(R) for R in P[:, :3, :3]])))
    # merged.ply: each side's cloud carried along with its keyframes into map
    own = {"front": sides["front"].keyframe_poses, "back": sides["back"].keyframe_poses}
    moved = clouds if clouds is not None else clouds_in_map(m, sides)
    write_labelled_cloud(out / MERGED_PLY, np.concatenate([moved["front"], moved["back"]]),
                         np.concatenate([sides["front"].cloud_colors, sides["back"].cloud_colors]),
                         np.repeat([0, 1], [len(moved["front"]), len(moved["back"])]))
    if al is not None:  # row.png, in the front side's canonical frame of the initial alignment
        Ta = al.T_front_back
        bases = {side: np.array([t.base for t in sides[side].trunks]).reshape(-1, 3) for side in poses}
        before = RowView("before: initial alignment", {
            "front": sides["front"].cloud_points,
            "back": sides["back"].cloud_points @ Ta[:3, :3].T + Ta[:3, 3]},
            {"front": bases["front"], "back": bases["back"] @ Ta[:3, :3].T + Ta[:3, 3]})
        label = {"semantic_ba": "semantic BA", "initial": "initial transform"}.get(m.method, m.method)
        after = RowView(f"after: {label}", moved, {
            side: move_with_keyframes(bases[side], own[side], poses[side]) for side in poses},
            tuple((np.asarray(t.position, float), t.height_m, tree_label(t, short=True)) for t in trees or []))
        write_row_png(out / ROW_PNG, al.front.T_canon_odom, [before, after], seed=0)


def tree_label(t: ResultTree, short: bool = False) -> str:
    """"tree <id>: trunk <mm>, height <m>, canopy <m3>", the title of trees/<id>.png; short: three lines (id,
    height, volume), its label in row.png (~0.5 inch of width per tree)."""
    d = f"{1000 * t.trunk_diameter_m:.0f} mm" if t.trunk_diameter_m else "n/a"
    h = f"{t.height_m:.2f} m" if t.height_m is not None else "n/a"
    v = f"{t.canopy_volume_m3:.2f} m\u00b3" if t.canopy_volume_m3 is not None else "n/a"
    return f"{t.id}\n{h}\n{v}" if short else f"tree {t.id}: trunk {d}, height {h}, canopy {v}"


FRUIT_CSV_COLUMNS = ("id", "tree_id", "x_m", "y_m", "z_m", "diameter_m", "seen_from", "on_ground")


def write_fruit_csv(path: Path, fruit: TreeFruit) -> None:
    """fruit.csv: one line per fruit of the row, each once (map frame, m; seen_from front / back / both;
    on_ground: lying under its tree, not in its count), written atomically."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(FRUIT_CSV_COLUMNS)
    r = fruit.row
    for i in range(len(r.positions)):
        w.writerow([i, int(fruit.tree_id[i]), *(f"{v:.4f}" for v in r.positions[i]), f"{r.diameters_m[i]:.4f}",
                    r.seen_from[i], int(fruit.on_ground[i])])
    atomic_write_text(path, buf.getvalue())


def write_tree_cloud(out: Path, labels: RowLabels, trees: list[ResultTree] | None = None) -> None:
    """trees.laz: the merged cloud with each point's tree and class (io.laz), and with `trees`,
    trees/<id>.png: each tree's points from the front and the side (docs/results.md)."""
    write_laz(out / TREES_LAZ, labels.points, labels.colors, labels.classification, labels.tree_id, labels.side,
              recorded_s=labels.recorded_s)
    if labels.fruit is not None:
        write_fruit_csv(out / FRUIT_CSV, labels.fruit)
    for t in trees or []:
        mine = labels.tree_id == t.id
        if not mine.any():
            continue
        write_tree_png(out / TREE_FIGURES / f"{t.id}.png", tree_label(t),
                       (labels.points[mine] - np.asarray(t.position)) @ labels.R_row_map.T,
                       labels.classification[mine], t.height_m, t.extra.get("clear_trunk_height_m"))
