"""A drive along a whole block in one bag, end to end through the command line (issue 46, part 2): simulate,
`orchard-map run` (rows and sides from the camera's turns, each row merged and measured into row_<k>/,
block.csv), `orchard-map evaluate` against the block's truth.

Two rows of two trees here (~2 minutes on 2 cores: rendering and reconstructing each frame is most of it):
the turns a block adds (U-turn round each row end, the turn into the same alley the other way round between
rows) and the per-row folders are all there with two rows. The three-row block, with its figures:
`python benchmarks/block_drive.py` (docs/usage.md, "A whole block in one drive").
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from orchard_mapping.cli.main import app
from orchard_mapping.io.block import read_block
from orchard_mapping.io.results import read_trees

# `make test-slow` (and CI): a two-row block simulated and run, ~3 minutes
pytestmark = pytest.mark.slow

runner = CliRunner()
SEED = 3
# 10 Hz at 0.5 m/s, level camera: the front end keeps track round both kinds of turn (at 6 Hz, or at 0.7 m/s,
# it lost tens of frames on a row's back side, benchmarks/block_drive.py); true trunk masks, as the drive round
# one row is tested (test/conftest.py loop_row)
SIM_SETS = ("block.rows=2", "camera.rate_hz=10", "masks_every=1")
DIAMETER_TOL_MM = 4.0  # per tree, the two-side diameter; a side alone is off by 0.3-1.1 mm on average (README)


@pytest.fixture(scope="module")
def block_run(scratch, seed_offset) -> Iterator[tuple[Path, Path, dict, str]]:
    """(simulation folder, result folder, `evaluate --json` of it, what `run` printed)."""
    with scratch("block") as root:
        sim, out = root / "sim", root / "result"
        sets = [a for s in SIM_SETS for a in ("--set", s)]
        res = runner.invoke(app, ["simulate", "--scenario", "block", "--trees", "2", "--seed", str(SEED + seed_offset),
                                  "--compress", "--out", str(sim), *sets])
        assert res.exit_code == 0, res.output
        res = runner.invoke(app, ["run", str(sim / "block"), "--out", str(out), "--set", "trunks.source=masks",
                                  "--set", f"trunks.masks_dir={sim / 'masks' / 'block'}"])
        assert res.exit_code == 0, res.output
        printed = res.output
        res = runner.invoke(app, ["evaluate", "--truth", str(sim / "ground_truth.json"), "--result", str(out),
                                  "--json"])
        assert res.exit_code == 0, res.output
        yield sim, out, json.loads(res.output), printed


def test_the_drive_is_cut_into_rows_and_sides_as_driven(block_run):
    sim, out, _, printed = block_run
    truth = json.loads((sim / "ground_truth.json").read_text())
    rows = read_block(out / "block.json")
    assert [(r.row, r.sides, r.status) for r in rows] == [(1, ("front", "back"), "measured"),
                                                          (2, ("front", "back"), "measured")]
    # each pass cut within 3 frames of where the simulator labels the turn (half way round): a frame is ~2 deg
    # of a U-turn here
    for r, tr in zip(rows, truth["rows"], strict=True):
        for p in r.passes:
            true = tr["passes"][p.side]
            assert abs(p.first_stamp - true["first_stamp"]) <= 0.31 and abs(p.last_stamp - true["last_stamp"]) <= 0.31
    # every frame in exactly one pass, in order
    frames = [f for r in rows for p in r.passes for f in range(p.first_frame, p.last_frame + 1)]
    assert frames == list(range(truth["drive"]["frames"]))
    for r in rows:
        assert f"row {r.row} (front" in printed and (out / r.folder / "side_merge.json").is_file()


@pytest.mark.accuracy
def test_every_tree_of_every_row_with_its_two_side_diameter(block_run, accuracy):
    sim, out, report, _ = block_run
    truth = json.loads((sim / "ground_truth.json").read_text())
    for row, tr in zip(report["rows"], truth["rows"], strict=True):
        m = row["report"]["matching"]
        assert m["matched"] == m["true_trees"] == len(tr["tree_ids"]) and m["missed"] == 0, (row["row"], m)
        # a tree found that is not one would be a post at the row's end, seen from one side only
        trees = {t.id: t for t in read_trees(out / f"row_{row['row']}" / "trees.json")}
        for fid in m["false_ids"]:
            assert {"seen_from_front_only", "seen_from_back_only"} & set(trees[fid].flags), trees[fid]
        for p in row["report"]["per_tree"]:
            t = trees[p["result_id"]]
            assert not {"seen_from_front_only", "seen_from_back_only"} & set(t.flags), t  # both sides' trunk
            err_mm = abs(p["est_trunk_diameter_m"] - p["true_trunk_diameter_m"]) * 1000
            accuracy.at_most(f"row {row['row']} tree {p['true_id']} trunk diameter error, mm", err_mm,
                             DIAMETER_TOL_MM)
        # the two sides merged on their trunks (not the fallback from global features)
        merge = json.loads((out / f"row_{row['row']}" / "side_merge.json").read_text())
        assert merge["method"] == "semantic_ba" and merge["overlap"]["pairs"] == len(tr["tree_ids"])
        accuracy.at_most(f"row {row['row']} merge rotation error, deg", row["report"]["merge"]["rotation_error_deg"],
                         2.0)


def test_block_csv_lists_every_tree_of_every_row(block_run):
    _, out, report, _ = block_run
    with (out / "block.csv").open(newline="") as f:
        lines = list(csv.DictReader(f))
    for row in report["rows"]:
        mine = [ln for ln in lines if ln["row"] == str(row["row"])]
        with (out / f"row_{row['row']}" / "trees.csv").open(newline="") as f:
            own = list(csv.DictReader(f))
        assert [{k: v for k, v in ln.items() if k != "row"} for ln in mine] == own
        # each tree's diameter from both sides, each side's own beside it
        assert all(ln["trunk_diameter_front_m"] and ln["trunk_diameter_back_m"] for ln in mine
                   if not ln["flags"]), mine
    timings = json.loads((out / "timings.json").read_text())
    assert {"front_end_front", "front_end_back", "merge"} <= set(timings["stages"])
