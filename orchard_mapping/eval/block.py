"""A block's result (pipeline.block: OUT/row_<k>/, block.json) against a simulated block's truth (sim.block).

Each row is scored by `evaluate_result` against that row's truth, re-anchored first: the product starts a side
where core.sides read the turn half way round from the tracked heading, the simulator where its path is half
way round, and the two may be a frame or two apart (a frame is ~4 deg of a turn at 10 Hz, ~10 cm at 4 m). A
side's odom frame is its first camera, so the row's truth is restated in the frames the result's sides begin
with (at the first keyframe of each, over the frames block.json gives its pass), from the whole drive in world
the simulator kept: the trees in map and each side's true trajectory then describe what the result describes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.table import Table

from orchard_mapping.core.geometry import pose_matrices
from orchard_mapping.errors import GroundTruthError
from orchard_mapping.eval.evaluate import evaluate_result
from orchard_mapping.eval.ground_truth import SIDES, parse_ground_truth
from orchard_mapping.eval.report import EvaluationReport
from orchard_mapping.io.block import BLOCK_JSON, MEASURED, BlockRowSummary, read_block
from orchard_mapping.io.results import load_json, read_tum, trajectory_filename

__all__ = ["BLOCK_TRUTH_SCHEMA", "BlockEvaluation", "RowEvaluation", "evaluate_block", "is_block_truth"]

BLOCK_TRUTH_SCHEMA = "orchard_mapping.block_ground_truth/1"  # sim.block writes it


def is_block_truth(path: str | Path) -> bool:
    """Whether the ground-truth file at path is a simulated block's (else a row's, or not readable as JSON)."""
    try:
        doc = load_json(Path(path), GroundTruthError, "ground-truth file")
    except GroundTruthError:
        return False
    return isinstance(doc, dict) and doc.get("schema") == BLOCK_TRUTH_SCHEMA


@dataclass(frozen=True)
class RowEvaluation:
    row: int
    true_trees: int
    result: BlockRowSummary | None  # None: the result has no such row
    report: EvaluationReport | None  # None: the row was not measured (result.message says why)


@dataclass(frozen=True)
class BlockEvaluation:
    truth_path: Path
    result_dir: Path
    rows: tuple[RowEvaluation, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"truth": str(self.truth_path), "result": str(self.result_dir), "rows": [{
            "row": r.row, "true_trees": r.true_trees,
            "status": r.result.status if r.result is not None else "absent",
            "message": r.result.message if r.result is not None else "no such row in the result",
            "report": r.report.to_dict() if r.report is not None else None,
        } for r in self.rows]}

    def table(self) -> Table:
        t = Table(title=f"block {self.result_dir} against {self.truth_path}")
        for col in ("row", "status", "trees matched", "missed", "false", "diameter MAE mm", "worst diameter mm",
                    "height MAE cm", "volume error %"):
            t.add_column(col, justify="left" if col == "status" else "right")
        for r in self.rows:
            status = r.result.status if r.result is not None else "absent"
            rep = r.report
            if rep is None or rep.matching is None:
                t.add_row(str(r.row), status, f"-/{r.true_trees}", "", "", "", "", "", "")
                continue
            m, tr = rep.matching, rep.traits
            worst = max((abs(p.est_trunk_diameter_m - p.true_trunk_diameter_m) * 1000 for p in rep.pairs
                         if p.est_trunk_diameter_m is not None), default=None)

            def f(v: float | None, fmt: str = ".1f") -> str:
                return "n/a" if v is None else format(v, fmt)

            t.add_row(str(r.row), status, f"{m.matched}/{m.true_trees}", str(m.missed), str(m.false),
                      f(tr.trunk_diameter_mae_mm if tr else None, ".2f"), f(worst, ".2f"),
                      f(tr.height_mae_cm if tr else None), f(tr.canopy_volume_mape_percent if tr else None))
        return t


def _drive_poses(drive: dict[str, Any], where: Path) -> tuple[np.ndarray, np.ndarray]:
    """(stamps (N,), T_world_cam (N, 4, 4)) of the simulated drive."""
    traj = np.asarray(drive["trajectory"], float)
    if traj.ndim != 2 or traj.shape[1] != 8:
        raise GroundTruthError(f"{where}: drive.trajectory: expected rows of 8 numbers")
    return traj[:, 0], pose_matrices(traj[:, 1:4], traj[:, 4:8])


def _tum_rows(stamps: np.ndarray, T_odom_cam: np.ndarray) -> list[list[float]]:
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(T_odom_cam[:, :3, :3]).as_quat()  # x y z w
    return [[float(s), *map(float, T[:3, 3]), *map(float, qq)] for s, T, qq in zip(stamps, T_odom_cam, q, strict=True)]


def _reanchored(row_doc: dict[str, Any], row: BlockRowSummary, row_dir: Path, stamps: np.ndarray,
                poses: np.ndarray, where: Path) -> dict[str, Any]:
    """The row's truth document restated in the result's frames: each side's odom frame placed in world from the
    result's first keyframe of that side (its true pose, times the inverse of the pose the result gives it: the
    front end starts a side's frame at the first frame it can place, not always the pass's first), its true
    trajectory over the frames of the result's pass of that side."""
    doc = dict(row_doc)
    sides = dict(doc["sides"])
    for p in row.passes:
        k0 = int(np.argmin(np.abs(stamps - p.first_stamp)))
        k1 = int(np.argmin(np.abs(stamps - p.last_stamp)))
        if abs(stamps[k0] - p.first_stamp) > 1e-3 or abs(stamps[k1] - p.last_stamp) > 1e-3:
            raise GroundTruthError(f"{where}: the result's {p.side} side of row {row.row} spans "
                                   f"{p.first_stamp:.3f}-{p.last_stamp:.3f} s, stamps the simulated drive does not "
                                   "have (another simulation's result?)")
        est = read_tum(row_dir / trajectory_filename(p.side))
        k = int(np.argmin(np.abs(stamps - est.stamps[0])))
        if abs(stamps[k] - est.stamps[0]) > 1e-3:
            raise GroundTruthError(f"{where}: the result's first {p.side} keyframe of row {row.row} "
                                   f"({est.stamps[0]:.3f} s) is no frame of the simulated drive")
        T_odom_cam0 = pose_matrices(est.positions[:1], est.quaternions[:1])[0]
        T_world_odom = poses[k] @ np.linalg.inv(T_odom_cam0)
        rel = np.linalg.inv(T_world_odom)[None] @ poses[k0:k1 + 1]
        pos = poses[k0:k1 + 1, :3, 3]
        sides[p.side] = dict(sides[p.side], T_world_odom=T_world_odom.tolist(),
                             trajectory=_tum_rows(stamps[k0:k1 + 1], rel),
                             path_length_m=float(np.sum(np.linalg.norm(np.diff(pos, axis=0), axis=1))),
                             duration_s=float(stamps[k1] - stamps[k0]))
    doc["sides"] = sides
    Tf = np.asarray(sides["front"]["T_world_odom"], float)
    Tb = np.asarray(sides["back"]["T_world_odom"], float)
    doc["T_front_back"] = (np.linalg.inv(Tf) @ Tb).tolist()
    return doc


def evaluate_block(truth_path: str | Path, result_dir: str | Path, match_radius_m: float = 0.3) -> BlockEvaluation:
    """Every row of the block's result against its truth (re-anchored at the result's sides, module docstring)."""
    truth_path, result_dir = Path(truth_path), Path(result_dir)
    truth = load_json(truth_path, GroundTruthError, "ground-truth file")
    if not isinstance(truth, dict) or truth.get("schema") != BLOCK_TRUTH_SCHEMA:
        raise GroundTruthError(f"{truth_path}: not a simulated block's truth (schema {BLOCK_TRUTH_SCHEMA!r})")
    try:
        stamps, poses = _drive_poses(truth["drive"], truth_path)
        true_rows = {int(r["row"]): r for r in truth["rows"]}
    except (KeyError, TypeError, ValueError) as err:
        raise GroundTruthError(f"{truth_path}: {err}") from err
    result_rows = {r.row: r for r in read_block(result_dir / BLOCK_JSON)}
    out = []
    for number, tr in sorted(true_rows.items()):
        row = result_rows.get(number)
        n_true = len(tr.get("tree_ids", ()))
        if row is None or row.status != MEASURED:
            out.append(RowEvaluation(number, n_true, row, None))
            continue
        row_truth = truth_path.parent / tr["truth"]
        row_doc = load_json(row_truth, GroundTruthError, "ground-truth file")
        if {p.side for p in row.passes} != set(SIDES):
            raise GroundTruthError(f"{result_dir / BLOCK_JSON}: row {number} is measured but its passes are "
                                   f"{[p.side for p in row.passes]}")
        gt = parse_ground_truth(_reanchored(row_doc, row, result_dir / row.folder, stamps, poses, row_truth),
                                row_truth)
        out.append(RowEvaluation(number, n_true, row, evaluate_result(gt, result_dir / row.folder,
                                                                      match_radius_m=match_radius_m)))
    return BlockEvaluation(truth_path, result_dir, tuple(out))
