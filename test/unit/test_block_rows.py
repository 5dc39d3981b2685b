"""pipeline.block: a drive's rows into their folders, block.csv and block.json (io.block); a row seen from one
side, or whose merge is refused, is flagged there and the run goes on. The merge itself is stubbed here (the
integration test test/integration/test_block_drive.py runs the real one)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from orchard_mapping.config import load_config
from orchard_mapping.core.sidemap import Observations, SideMap
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import AlignmentError, ResultFormatError
from orchard_mapping.io.block import (
    BLOCK_CSV,
    BLOCK_JSON,
    MEASURED,
    NOT_MERGED,
    ONE_SIDE,
    DrivePass,
    read_block,
)
from orchard_mapping.io.results import TREES_CSV_COLUMNS, ResultTree, read_trees
from orchard_mapping.pipeline import block
from orchard_mapping.pipeline.side import DriveRow
from orchard_mapping.pipeline.sides import Timings

INTR = CameraIntrinsics(640, 480, 615.0, 615.0, 319.5, 239.5)


def _side(name: str) -> SideMap:
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    empty = Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0))
    return SideMap(name, f"odom_{name}", INTR, np.arange(3.0), poses, np.zeros((0, 3)), empty, [],
                   np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), odometry_poses=poses)


def _row(number: int, sides: tuple[str, ...], last: bool = False) -> DriveRow:
    passes = tuple(DrivePass(s, 100 * number + 50 * k, 100 * number + 50 * k + 49, 10.0 * number + 5 * k,
                             10.0 * number + 5 * k + 4.9) for k, s in enumerate(sides))
    return DriveRow(number, {s: _side(s) for s in sides}, passes, Timings(), last)


@pytest.fixture
def stub_merge(monkeypatch):
    """merge_and_measure giving two trees per row (row 2's merge refused); the merge's files not written."""
    def merge(sides, cfg, worker):
        if sides["front"].keyframe_stamps is ROW2_STAMPS:
            raise AlignmentError("no trunk seen from both sides")
        trees = [ResultTree(id=i, position=(float(i), 0.5, 0.0), trunk_diameter_m=0.07 + 0.001 * i,
                            height_m=2.0, canopy_volume_m3=0.4) for i in range(2)]
        return None, {}, trees, None, 0.0
    monkeypatch.setattr(block, "merge_and_measure", merge)
    monkeypatch.setattr(block, "write_merge", lambda *a, **k: None)
    monkeypatch.setattr(block, "write_tree_cloud", lambda *a, **k: None)


ROW2_STAMPS = np.arange(3.0)


def test_rows_are_written_each_in_its_folder_and_flagged_when_not_measured(tmp_path, stub_merge):
    cfg = load_config()
    rows = [_row(1, ("front", "back")), _row(2, ("front", "back")), _row(3, ("front",), last=True)]
    object.__setattr__(rows[1].sides["front"], "keyframe_stamps", ROW2_STAMPS)
    timings = Timings()
    result = block.run_block(tmp_path, rows, cfg, None, timings)
    assert [r.status for r in result.rows] == [MEASURED, NOT_MERGED, ONE_SIDE]
    assert [r.row for r in result.refused] == [2]
    assert "not merged: no trunk seen from both sides" in result.rows[1].message
    assert "front side only" in result.rows[2].message and "back" in result.rows[2].message
    # each row its usual folder: the sides' own files always, the trees where it was measured
    for k in (1, 2, 3):
        names = {p.name for p in (tmp_path / f"row_{k}").iterdir()}
        assert {"trajectory_front.tum", "trunks.json", "timings.json", "config.effective.yaml"} <= names
        assert ("trees.csv" in names) == (k == 1)
    assert len(read_trees(tmp_path / "row_1" / "trees.json")) == 2
    assert not any(p.name.startswith(".staging") for p in tmp_path.iterdir())
    # block.csv: the row, then trees.csv's columns, one line per tree of every measured row
    with (tmp_path / BLOCK_CSV).open(newline="") as f:
        lines = list(csv.reader(f))
    assert lines[0][:len(TREES_CSV_COLUMNS) + 1] == ["row", *TREES_CSV_COLUMNS]
    assert [(line[0], line[1]) for line in lines[1:]] == [("1", "0"), ("1", "1")]
    assert float(lines[2][5]) == pytest.approx(0.071)
    # block.json read back
    again = read_block(tmp_path / BLOCK_JSON)
    assert again == result.rows
    assert again[2].passes[0].frames == 50 and again[2].sides == ("front",)


def test_a_second_run_replaces_a_rows_folder_whole(tmp_path, stub_merge):
    cfg = load_config()
    block.run_block(tmp_path, [_row(1, ("front", "back"), last=True)], cfg, None, Timings())
    assert (tmp_path / "row_1" / "trees.csv").is_file()
    block.run_block(tmp_path, [_row(1, ("back",), last=True)], cfg, None, Timings())
    assert not (tmp_path / "row_1" / "trees.csv").exists()  # no earlier run's trees beside this run's side
    assert read_block(tmp_path / BLOCK_JSON)[0].status == ONE_SIDE


def test_a_block_summary_that_is_not_one_is_refused_naming_the_file(tmp_path):
    (tmp_path / BLOCK_JSON).write_text('{"schema": "orchard_mapping.block/1", "rows": [{"row": 1}]}')
    with pytest.raises(ResultFormatError, match=r"block.json: rows\[0\]"):
        read_block(tmp_path / BLOCK_JSON)
    (tmp_path / BLOCK_JSON).write_text('{"schema": "other"}')
    with pytest.raises(ResultFormatError, match="not a block summary"):
        read_block(tmp_path / BLOCK_JSON)
