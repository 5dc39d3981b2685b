"""A block's result folder (a drive along several rows, docs/results.md): OUT/row_<k>/ per row (the usual result
folder), OUT/block.csv (every tree of every row measured: the row, then trees.csv's columns) and OUT/block.json
(each row's sides, passes and status). Written by pipeline.block, read by eval.block."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from orchard_mapping.errors import ResultFormatError
from orchard_mapping.io.results import (
    TREES_CSV_COLUMNS,
    TREES_CSV_MORE_COLUMNS,
    atomic_write_json,
    atomic_write_text,
    load_json,
)

__all__ = [
    "BLOCK_CSV",
    "BLOCK_JSON",
    "BLOCK_SCHEMA",
    "MEASURED",
    "NOT_MEASURED",
    "NOT_MERGED",
    "ONE_SIDE",
    "DrivePass",
    "BlockRowSummary",
    "read_block",
    "row_folder",
    "write_block",
]

BLOCK_CSV = "block.csv"
BLOCK_JSON = "block.json"
BLOCK_SCHEMA = "orchard_mapping.block/1"
# A row's status in block.json
MEASURED = "measured"  # both sides merged, its trees measured
ONE_SIDE = "one_side"  # the drive went along one side of it only: that side's reconstruction, no trees
NOT_MERGED = "not_merged"  # both sides, but the merge was refused: each side's reconstruction, no trees
NOT_MEASURED = "not_measured"  # trunks or the merge switched off by the configuration
STATUSES = (MEASURED, ONE_SIDE, NOT_MERGED, NOT_MEASURED)


def row_folder(number: int) -> str:
    """`row_<k>`: row k's folder in a block's result (and in a simulated block's truth)."""
    return f"row_{number}"


@dataclass(frozen=True)
class DrivePass:
    """One pass of the drive: its frames along one side of a row, from one turn to the next (half way round)."""

    side: str
    first_frame: int
    last_frame: int
    first_stamp: float  # s
    last_stamp: float  # s

    @property
    def frames(self) -> int:
        return self.last_frame - self.first_frame + 1


@dataclass(frozen=True)
class BlockRowSummary:
    """One row as block.json states it."""

    row: int  # 1, 2, ...: in the order driven
    folder: str  # row_<k>, inside the block's folder
    status: str  # one of STATUSES
    message: str  # why it was not measured ("" where it was)
    sides: tuple[str, ...]  # the sides the drive went along
    trees: int  # trees measured
    keyframes: dict[str, int]  # per side
    passes: tuple[DrivePass, ...]


def write_block(out: Path, rows: Iterable[BlockRowSummary]) -> None:
    """block.csv (each measured row's trees.csv under a `row` column) and block.json into `out`."""
    rows = list(rows)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["row", *TREES_CSV_COLUMNS, *TREES_CSV_MORE_COLUMNS])
    for r in rows:
        path = out / r.folder / "trees.csv"
        if r.status != MEASURED or not path.is_file():
            continue
        with path.open(newline="") as f:
            lines = list(csv.reader(f))
        if lines[0] != [*TREES_CSV_COLUMNS, *TREES_CSV_MORE_COLUMNS]:
            raise ResultFormatError(f"{path}: its columns are not trees.csv's ({lines[0][:4]}...)")
        w.writerows([r.row, *line] for line in lines[1:])
    atomic_write_text(out / BLOCK_CSV, buf.getvalue())
    atomic_write_json(out / BLOCK_JSON, {
        "schema": BLOCK_SCHEMA,
        # each row is merged on its own: its trees' positions are in that row's map frame (its front side's
        # first camera), not in one frame of the block
        "frames": "per row: map of row_<k> (its front side's first camera)",
        "rows": [{
            "row": r.row, "folder": r.folder, "status": r.status, "message": r.message, "sides": list(r.sides),
            "trees": r.trees, "keyframes": r.keyframes,
            "passes": [{"side": p.side, "first_frame": p.first_frame, "last_frame": p.last_frame,
                        "first_stamp": p.first_stamp, "last_stamp": p.last_stamp, "frames": p.frames}
                       for p in r.passes],
        } for r in rows],
    })


def _row(d: Any, path: Path, where: str) -> BlockRowSummary:
    try:
        status = d["status"]
        if status not in STATUSES:
            raise ValueError(f"status {status!r} is none of {', '.join(STATUSES)}")
        passes = tuple(DrivePass(str(p["side"]), int(p["first_frame"]), int(p["last_frame"]),
                                 float(p["first_stamp"]), float(p["last_stamp"])) for p in d["passes"])
        return BlockRowSummary(int(d["row"]), str(d["folder"]), status, str(d["message"]),
                               tuple(str(s) for s in d["sides"]), int(d["trees"]),
                               {str(k): int(v) for k, v in d["keyframes"].items()}, passes)
    except (KeyError, TypeError, ValueError, AttributeError) as err:
        raise ResultFormatError(f"{path}: {where}: {err}") from err


def read_block(path: str | Path) -> tuple[BlockRowSummary, ...]:
    """The rows of block.json (ResultFormatError naming the file and field when it is not one)."""
    path = Path(path)
    doc = load_json(path, ResultFormatError, "block summary")
    if not isinstance(doc, dict) or doc.get("schema") != BLOCK_SCHEMA:
        raise ResultFormatError(f"{path}: not a block summary (schema {BLOCK_SCHEMA!r})")
    rows = doc.get("rows")
    if not isinstance(rows, list):
        raise ResultFormatError(f"{path}: rows: expected a list")
    return tuple(_row(d, path, f"rows[{i}]") for i, d in enumerate(rows))
