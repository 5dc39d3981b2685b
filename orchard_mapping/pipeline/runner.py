"""`run`: bags in, result folder out (docs/results.md), staged so that a failed run leaves no half-written
result."""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from orchard_mapping.config import OrchardConfig, dump_yaml
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.errors import AlignmentError, MergeRefusedError
from orchard_mapping.io.results import atomic_write_text, staged_folder, write_timings, write_trees
from orchard_mapping.pipeline.block import BlockResult, run_block
from orchard_mapping.pipeline.outputs import (
    RUN_OUTPUTS,
    write_inputs,
    write_landmarks,
    write_merge,
    write_side,
    write_tree_cloud,
)
from orchard_mapping.pipeline.side import PendingSide, drive_rows, reconstruct_side_later
from orchard_mapping.pipeline.sides import DRIVE, SIDES, Progress, Timings, open_sides, side_mask
from orchard_mapping.pipeline.traits import merge_and_measure
from orchard_mapping.pipeline.trunks import TrunkWorker

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunResult:
    out_dir: Path
    sides: dict[str, SideMap]
    timings: Timings
    merge_refused: str | None = None  # why the sides were not merged (run raises MergeRefusedError)
    block: BlockResult | None = None  # a drive along several rows: each row's folder and how it went


def run(front: str | Path, back: str | Path | None, out: str | Path, cfg: OrchardConfig,
        progress: Progress | None = None, trunk_worker: bool = False) -> RunResult:
    """Reconstruct each side and write the result folder.

    trunk_worker: model the first side's trunks, the last side's posts and half the merge's two-side fits in
    a spawned worker process (TrunkWorker; same results). `orchard-map run` does. A spawned process imports the
    caller's main module again: a script that calls this with trunk_worker=True needs the
    `if __name__ == "__main__":` guard that Python's multiprocessing asks for.

    Everything is written into a staging folder first and moved into `out` only when the whole run
    succeeded: a failed run leaves no half-written result (earlier results in `out` stay as they were).
    """
    out = Path(out)
    # RUN_OUTPUTS: the set written replaces an earlier run's whole, its merge outputs included where this
    # run's merge was refused (they would contradict the sides now beside them)
    with staged_folder(out, replaces=RUN_OUTPUTS) as stage:
        result = _run(Path(front), Path(back) if back is not None else None, stage, cfg, progress, trunk_worker,
                      rows_out=out)
    if result.block is not None and result.block.refused:
        rows = result.block.refused
        raise MergeRefusedError(
            f"{len(rows)} row(s) of the block not merged: {'; '.join(f'row {r.row}: {r.message}' for r in rows)}. "
            f"Each row's results are in {out}/row_<k>; block.csv lists the trees of the rows measured.")
    if result.merge_refused is not None:
        # The sides' own results are complete and stay; the merge is not guessed (exit code 2).
        raise MergeRefusedError(
            f"the two sides were not merged: {result.merge_refused}. Each side's results (trajectories, "
            f"clouds, trunks.json) are in {out}; no side_merge.json and no trees in map were written. "
            "Run with --set merge.method=off to reconstruct the sides without trying to merge them.")
    return RunResult(out, result.sides, result.timings, result.merge_refused, result.block)


def _one_side(sides: dict[str, SideMap], bag: Path, cfg: OrchardConfig, drive: bool) -> str:
    """Why a merge asked for cannot be made of one bag that gave one side only."""
    have = ", ".join(sides) or "no"
    missing = " and ".join(s for s in SIDES if s not in sides)
    if drive:
        why = (f"the camera's path in {bag} has no U-turn to the {missing} side (a recording of one side? give "
               f"the {missing} side's bag as the second bag)")
    else:
        why = f"the side topic {cfg.input.topics.side} labels no frame of {bag} '{missing}'"
    return f"only the {have} side is in the input: {why}"


def _run(front: Path, back: Path | None, out: Path, cfg: OrchardConfig, progress: Progress | None,
         trunk_worker: bool, rows_out: Path | None = None) -> RunResult:
    """The run into `out` (run's staging folder); the rows of a drive along a block go to rows_out (each row's
    folder written whole as it is done) and block.csv, block.json into `out`."""
    timings = Timings()
    t0 = t_start = time.perf_counter()
    seqs = open_sides(front, back, cfg)
    timings.add("read_bags", time.perf_counter() - t0)
    write_inputs(out, seqs)
    drive = DRIVE in seqs
    labelled = back is None
    sides: dict[str, SideMap] = {}
    refused: str | None = None
    # Two sides with trunks: the first side's trunks are modelled in a worker process while the next is finished
    abandon = False
    worker = (TrunkWorker() if trunk_worker and cfg.trunks.source != "off" and cfg.input.mode == "rgbd"
              and (DRIVE in seqs or len(seqs) > 1) else None)
    try:
        if DRIVE in seqs:
            seq = seqs.pop(DRIVE)
            timings.frames += len(seq)
            timings.recording_duration_s += seq.duration
            rows = drive_rows(seq, cfg, progress, worker)
            row = next(rows, None)
            if row is not None and not row.last:  # the drive went on along more rows: one result per row
                block = run_block(rows_out or out, itertools.chain([row], rows), cfg, worker, timings)
                return _block_done(out, cfg, timings, t_start, block)
            for stage, sec in (row.timings.stages.items() if row is not None else ()):
                timings.add(stage, sec)
            for side, sm in (row.sides.items() if row is not None else ()):
                sides[side] = sm
                write_side(out, sm)
        pending: dict[str, PendingSide] = {}
        for i, (side, seq) in enumerate(seqs.items()):
            timings.frames += int(np.sum(side_mask(seq, side))) if labelled else len(seq)
            if labelled:
                st = seq.stamps[side_mask(seq, side)]
                timings.recording_duration_s += float(st[-1] - st[0]) if len(st) > 1 else 0.0
            else:
                timings.recording_duration_s += seq.duration
            pending[side] = reconstruct_side_later(seq, side, cfg, timings, labelled, progress, worker,
                                                   here=i == len(seqs) - 1)
        for side, p in pending.items():
            sides[side] = p()
            write_side(out, sides[side])
        if cfg.trunks.source != "off" and cfg.input.mode == "rgbd":
            write_landmarks(out, sides, cfg)
            if cfg.merge.method != "off" and set(sides) != set(SIDES):
                refused = _one_side(sides, front, cfg, drive)
                log.warning("side merge refused: %s", refused)
            elif cfg.merge.method != "off":
                t0 = time.perf_counter()
                traits_s = 0.0
                try:
                    merged, clouds, trees, labels, traits_s = merge_and_measure(sides, cfg, worker)
                except AlignmentError as err:
                    log.warning("side merge refused: %s (no side_merge.json written)", err)
                    refused = str(err)
                else:
                    timings.merge_steps = dict(merged.seconds)
                    write_merge(out, merged, sides, clouds, trees)
                    write_trees(out, trees, frame="map")
                    write_tree_cloud(out, labels, trees)
                timings.add("merge", time.perf_counter() - t0 - traits_s)
                timings.add("traits", traits_s)
    except BaseException:
        abandon = True  # the run is over (an error, Ctrl-C): the worker's job is not waited for
        raise
    finally:
        if worker is not None:
            worker.close(abandon=abandon)
    timings.wall_s = time.perf_counter() - t_start
    write_timings(out / "timings.json", timings.stages, frames=timings.frames,
                  recording_duration_s=timings.recording_duration_s, wall_s=timings.wall_s,
                  merge_steps=timings.merge_steps)
    atomic_write_text(out / "config.effective.yaml", dump_yaml(cfg))
    return RunResult(out, sides, timings, refused)


def _block_done(out: Path, cfg: OrchardConfig, timings: Timings, t_start: float, block: BlockResult) -> RunResult:
    """The end of a block's run: the whole run's timings and configuration beside block.csv (each row has its own)."""
    timings.wall_s = time.perf_counter() - t_start
    write_timings(out / "timings.json", timings.stages, frames=timings.frames,
                  recording_duration_s=timings.recording_duration_s, wall_s=timings.wall_s)
    atomic_write_text(out / "config.effective.yaml", dump_yaml(cfg))
    return RunResult(out, {}, timings, None, block)
