"""A drive along a whole block (row after row, both sides of each): one result folder per row and the block's
summary (docs/usage.md, "A whole block in one drive").

`pipeline.side.drive_rows` cuts the drive into rows and sides at its turns and reconstructs each row's sides;
each row is then merged and measured as a drive round one row is, and written, whole or not at all, into
OUT/row_<k>/ (the usual result folder) as soon as it is done: a run stopped at row 5 keeps rows 1-4. At the
end OUT/block.csv lists every tree of every row measured (the row, then trees.csv's columns) and
OUT/block.json says for each row which sides the drive went along, its passes, and whether and why it was
not measured (a row driven along one side only, a merge refused): such a row is flagged there, never the end
of the run.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from orchard_mapping.config import OrchardConfig, dump_yaml
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.errors import AlignmentError
from orchard_mapping.io.block import (
    MEASURED,
    NOT_MEASURED,
    NOT_MERGED,
    ONE_SIDE,
    BlockRowSummary,
    row_folder,
    write_block,
)
from orchard_mapping.io.results import TIMINGS_JSON, atomic_write_text, staged_folder, write_timings, write_trees
from orchard_mapping.pipeline.outputs import write_landmarks, write_merge, write_side, write_tree_cloud
from orchard_mapping.pipeline.side import DriveRow
from orchard_mapping.pipeline.sides import SIDES, Timings
from orchard_mapping.pipeline.traits import merge_and_measure
from orchard_mapping.pipeline.trunks import TrunkWorker

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BlockResult:
    out_dir: Path
    rows: tuple[BlockRowSummary, ...]  # as block.json states them (their folders inside out_dir)

    @property
    def refused(self) -> tuple[BlockRowSummary, ...]:
        """The rows driven along both sides whose merge was refused."""
        return tuple(r for r in self.rows if r.status == NOT_MERGED)


def _measure_row(out: Path, sides: dict[str, SideMap], cfg: OrchardConfig, worker: TrunkWorker | None,
                 timings: Timings) -> tuple[str, str, int]:
    """A row's sides, merge and trees into `out`, as `orchard-map run` writes a drive round one row
    (pipeline.runner): (status, message, trees)."""
    for sm in sides.values():
        write_side(out, sm)
    if cfg.trunks.source == "off" or cfg.input.mode != "rgbd":
        return NOT_MEASURED, "no trunks (trunks.source off, or colour only): each side's reconstruction only", 0
    write_landmarks(out, sides, cfg)
    if cfg.merge.method == "off":
        return NOT_MEASURED, "merge.method is off: each side's reconstruction only", 0
    if set(sides) != set(SIDES):
        missing = " and ".join(s for s in SIDES if s not in sides)
        return ONE_SIDE, (f"the drive went along its {', '.join(sides)} side only (no U-turn round its end to the "
                          f"{missing} side): that side's reconstruction, no trees"), 0
    t0 = time.perf_counter()
    try:
        merged, clouds, trees, labels, traits_s = merge_and_measure(sides, cfg, worker)
    except AlignmentError as err:
        timings.add("merge", time.perf_counter() - t0)
        return NOT_MERGED, f"the two sides were not merged: {err}", 0
    write_merge(out, merged, sides, clouds, trees)
    write_trees(out, trees, frame="map")
    write_tree_cloud(out, labels, trees)
    timings.add("merge", time.perf_counter() - t0 - traits_s)
    timings.add("traits", traits_s)
    return MEASURED, "", len(trees)


def write_row(out: Path, row: DriveRow, cfg: OrchardConfig, worker: TrunkWorker | None) -> BlockRowSummary:
    """Row `row` into OUT/row_<k>/, whole or not at all (an earlier run's folder of that row is replaced)."""
    t0 = time.perf_counter()
    name = row_folder(row.row)
    with staged_folder(out) as stage:
        folder = stage / name
        folder.mkdir()
        status, message, n_trees = _measure_row(folder, row.sides, cfg, worker, row.timings)
        row.timings.wall_s = time.perf_counter() - t0
        write_timings(folder / TIMINGS_JSON, row.timings.stages, frames=row.timings.frames,
                      recording_duration_s=row.timings.recording_duration_s, wall_s=row.timings.wall_s)
        atomic_write_text(folder / "config.effective.yaml", dump_yaml(cfg))
    if status != MEASURED:
        log.warning("row %d not measured: %s", row.row, message)
    else:
        log.info("row %d: %d trees", row.row, n_trees)
    return BlockRowSummary(row.row, name, status, message, tuple(row.sides), n_trees,
                           {side: len(sm.keyframe_stamps) for side, sm in row.sides.items()}, row.passes)


def run_block(out: Path, rows: Iterable[DriveRow], cfg: OrchardConfig, worker: TrunkWorker | None,
              timings: Timings) -> BlockResult:
    """Every row of a drive along a block (drive_rows) into its folder as it comes, then block.csv and
    block.json into `out`. timings: the run's, to which every row's stages are added."""
    out = Path(out)
    done: list[BlockRowSummary] = []
    for row in rows:
        done.append(write_row(out, row, cfg, worker))
        for stage, sec in row.timings.stages.items():
            timings.add(stage, sec)
    write_block(out, done)
    return BlockResult(out, tuple(done))
