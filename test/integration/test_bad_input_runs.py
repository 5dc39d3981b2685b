"""The bad-input suite (issue 46), whole runs: the cases that need `orchard-map run` to go some way before the
outcome shows. Each ends in a typed error (one line, exit code 2, the folder as it was), or in a partial result
that says so (inputs.json's flags, a tree's flags, exit code 2 with the sides' own files), or in exit code 130
on Ctrl-C; never a traceback, never a half-written folder. The recordings: a simulated row of one tree, small
(320 x 240, 6 Hz: its sides track, and the run takes ~10 s), and the committed 2-tree fixtures (bags/), on which
the shipped detector finds no trunk. The recording-level cases are in test/unit/io/test_bad_input.py;
docs/bad_input.md lists every case.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from orchard_mapping.cli.main import app
from orchard_mapping.config import load_config
from orchard_mapping.eval import evaluate_result
from orchard_mapping.io.bag_writer import BagWriter
from orchard_mapping.io.bags import describe_bag, read_rgbd
from orchard_mapping.io.results import read_trees

BAGS = Path(__file__).resolve().parents[2] / "bags" / "standard_2trees"
T = load_config().input.topics


@pytest.fixture(scope="module")
def row(scratch) -> Iterator[Path]:
    """A row of one tree, both sides, true trunk masks for every frame (~6 s to simulate)."""
    from orchard_mapping.sim.scenario import load_scenario
    from orchard_mapping.sim.simulate import simulate

    sc = load_scenario("single_pass", {
        "row.n_trees": 1, "row.margin_m": 0.6, "masks_every": 1, "camera.rate_hz": 6, "camera.width": 320,
        "camera.height": 240, "camera.fx": 307.5, "camera.fy": 307.5, "camera.cx": 159.5, "camera.cy": 119.5})
    with scratch("bad_input_row") as root:
        yield simulate(sc, 6, root / "row").out_dir


def _run(*args: str | Path) -> tuple[int, str]:
    res = CliRunner().invoke(app, ["run", *(str(a) for a in args)])
    assert "Traceback" not in res.output, res.output
    return res.exit_code, res.output


def _with_masks(row: Path, masks: Path | None = None) -> list[str]:
    return ["--set", "trunks.source=masks", "--set", f"trunks.masks_dir={masks or row / 'masks'}"]


@pytest.fixture(scope="module")
def one_tree_result(row, scratch) -> Iterator[Path]:
    """`orchard-map run` on the row of one tree, trunks from the true masks: a complete result folder."""
    with scratch("bad_input_result") as root:
        out = root / "result"
        code, output = _run(row / "front", row / "back", "--out", out, *_with_masks(row))
        assert code == 0, output
        yield out


def _listing(folder: Path) -> dict[str, bytes]:
    """Every file under folder (relative path -> content): what a failed run must leave as it was."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# --------------------------------------------------------------------------- partial results, flagged


def test_a_row_of_one_tree_is_merged_from_global_features_and_every_tree_flagged(row, one_tree_result):
    # one trunk seen from both sides is fewer than the semantic merge's two pairs: the sides are merged from the
    # global features alone, and every tree says so
    merge = json.loads((one_tree_result / "side_merge.json").read_text())
    assert merge["method"] == "global_features"
    trees = read_trees(one_tree_result / "trees.json")
    assert trees and all("merged_by_global_features" in t.flags for t in trees)
    assert evaluate_result(row / "ground_truth.json", one_tree_result).to_dict()["matching"]["matched"] == 1
    assert json.loads((one_tree_result / "inputs.json").read_text())["flags"] == []


def _rewrite(src: Path, dst: Path, stamp_of) -> None:
    """src's frames into the bag dst, frame i at stamp_of(i, stamp) (a list of stamps: written once each)."""
    seq = read_rgbd(src)
    with BagWriter(dst) as bag:
        bag.write_camera_info(T.camera_info, 0.0, seq.intrinsics)
        for f in seq:
            for t in np.atleast_1d(stamp_of(f.index, f.stamp)):
                bag.write_color(T.color, float(t), f.color)
                bag.write_depth(T.depth, float(t), f.depth)


def test_a_cut_recording_a_gap_and_repeated_stamps_are_flagged_in_inputs_json(row, tmp_path, caplog):
    # front: its MCAP file cut at 80 % of its bytes (the vehicle lost power), metadata.yaml from its close kept
    cut = tmp_path / "front"
    shutil.copytree(row / "front", cut)
    mcap = next(cut.glob("*.mcap"))
    mcap.write_bytes(mcap.read_bytes()[: int(0.8 * mcap.stat().st_size)])
    # back: frame 3 written twice, and 5 s without frames after frame 7
    back = tmp_path / "back"
    _rewrite(row / "back", back, lambda i, t: [t, t] if i == 3 else t + (5.0 if i > 7 else 0.0))
    out = tmp_path / "result"
    code, output = _run(cut, back, "--out", out, "--set", "trunks.source=off")
    assert code == 0, output
    inputs = json.loads((out / "inputs.json").read_text())
    assert inputs["schema"] == "orchard_mapping.inputs/1"
    front, rear = inputs["bags"]
    assert front["bag"] == str(cut) and front["sides"] == ["front"] and "cut_short" in front["flags"]
    kept = front["cut_short"]["messages_kept"]
    recorded = sum(n for _, _, n in describe_bag(row / "front").topics)  # what the whole file holds
    assert front["cut_short"]["messages_lost"] == recorded - kept > 0
    assert front["frames"] < len(read_rgbd(row / "front")) and (out / "trajectory_front.tum").is_file()
    assert rear["flags"] == ["stamp_gap", "duplicate_stamps"] and rear["duplicate_stamps"] == 1
    ((before, after),) = rear["gaps_s"]
    assert after - before == pytest.approx(5.0 + 1 / 6, abs=1e-6)
    assert inputs["flags"] == ["cut_short", "duplicate_stamps", "stamp_gap"]
    # ...and said as the run went (the command's log lines: warnings, on stderr)
    assert f"{mcap} is cut short" in caplog.text and f"{back}: a gap of 5.2 s without frames" in caplog.text


def test_no_trunk_in_a_side_keeps_the_sides_and_refuses_the_merge_with_exit_code_2(row, tmp_path):
    masks = tmp_path / "masks"  # true masks for the front side; none at all for the back side
    shutil.copytree(row / "masks" / "front", masks / "front")
    (masks / "back").mkdir()
    (masks / "back" / "index.csv").write_text("frame,stamp\n")
    out = tmp_path / "result"
    code, output = _run(row / "front", row / "back", "--out", out, *_with_masks(row, masks),
                        "--set", "trunks.geometric=off")
    assert code == 2, output
    text = " ".join(output.split())
    assert "error: the two sides were not merged" in text and "(front 1, back 0 trunks)" in text
    assert "merge.method=off" in text
    trunks = json.loads((out / "trunks.json").read_text())["sides"]
    assert len(trunks["front"]["trunks"]) == 1 and trunks["back"]["trunks"] == []
    assert (out / "trajectory_back.tum").is_file() and not (out / "side_merge.json").exists()
    assert not (out / "trees.json").exists() and not list(out.glob(".staging-*"))


def test_one_side_missing_keeps_that_side_and_refuses_the_merge_with_exit_code_2(tmp_path):
    # the front side's bag alone: no side topic, and its camera path has no U-turn to a back side
    out = tmp_path / "result"
    code, output = _run(BAGS / "front", "--out", out)
    assert code == 2, output
    text = " ".join(output.split())
    assert "only the front side is in the input" in text and "no U-turn to the back side" in text
    assert str(BAGS / "front") in text
    assert (out / "trajectory_front.tum").is_file() and not (out / "trees.json").exists()
    assert json.loads((out / "inputs.json").read_text())["bags"][0]["sides"] == ["drive"]
    # asked for one side only, it is a whole result
    code, output = _run(BAGS / "front", "--out", tmp_path / "one_side", "--set", "merge.method=off")
    assert code == 0, output


# --------------------------------------------------------------------------- the result folder


def test_a_second_run_into_a_folder_replaces_the_earlier_result_whole(one_tree_result, row, tmp_path):
    out = tmp_path / "result"
    shutil.copytree(one_tree_result, out)
    (out / "notes.txt").write_text("mine")
    code, output = _run(row / "front", row / "back", "--out", out, "--set", "trunks.source=off")
    assert code == 0, output
    # nothing of the merged run stays beside a run without trunks as if it were its own
    left = {p.name for p in out.iterdir()}
    assert left == {"notes.txt", "inputs.json", "timings.json", "config.effective.yaml", "front.ply", "back.ply",
                    "trajectory_front.tum", "trajectory_back.tum", "odometry_front.tum", "odometry_back.tum"}
    assert load_config(out / "config.effective.yaml").trunks.source == "off"


@pytest.mark.parametrize("where", ["fsync", "point cloud"])
def test_a_full_disk_is_one_typed_error_and_the_earlier_result_stays(where, one_tree_result, row, tmp_path,
                                                                     monkeypatch):
    out = tmp_path / "result"
    shutil.copytree(one_tree_result, out)
    before = _listing(out)
    if where == "fsync":  # the disk fills up after a few files of the run were written
        calls = {"n": 0}
        real = os.fsync

        def fsync(fd: int) -> None:
            calls["n"] += 1
            if calls["n"] > 2:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            real(fd)
        monkeypatch.setattr(os, "fsync", fsync)
        says = "No space left on device"
    else:  # Open3D only answers False when it cannot write a cloud (a full disk among other causes)
        import open3d as o3d

        monkeypatch.setattr(o3d.io, "write_point_cloud", lambda *a, **k: False)
        says = "could not write the point cloud (" + str(out)
    code, output = _run(row / "front", row / "back", "--out", out, "--set", "trunks.source=off")
    assert code == 2, output
    text = " ".join(output.split())
    assert "error: cannot write the results:" in text and says in text and f"(folder {out})" in text
    assert _listing(out) == before and not list(out.glob(".staging-*"))


@pytest.mark.parametrize("kind", ["a file where the folder goes", "no permission"])
def test_an_unwritable_output_folder_is_one_typed_error(kind, tmp_path, monkeypatch):
    if kind == "a file where the folder goes":
        (tmp_path / "taken").write_text("a file")
        out = tmp_path / "taken" / "result"
        says = "Not a directory"
    else:
        # as root (CI containers) a folder's mode does not stop a write, so the refusal the kernel gives a user
        # is raised where the run makes its staging folder
        out = tmp_path / "shared" / "result"
        import tempfile

        real = tempfile.mkdtemp

        def mkdtemp(*args, **kw):
            if Path(kw.get("dir", "")).absolute() == out.absolute():
                raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(out))
            return real(*args, **kw)
        monkeypatch.setattr(tempfile, "mkdtemp", mkdtemp)
        says = "Permission denied"
    code, output = _run(BAGS / "front", BAGS / "back", "--out", out, "--set", "trunks.source=off")
    assert code == 2, output
    text = " ".join(output.split())
    assert "error: cannot write the results:" in text and says in text and f"(folder {out})" in text
    assert not out.exists() and not (tmp_path / "shared").exists()


# --------------------------------------------------------------------------- Ctrl-C


@pytest.mark.parametrize("when", ["reading the first side", "as the trunk worker starts"])
def test_ctrl_c_exits_130_and_leaves_the_folder_as_it_was(when, one_tree_result, tmp_path):
    import psutil

    out = tmp_path / "result"
    shutil.copytree(one_tree_result, out)
    before = _listing(out)
    # The command as installed (not `python -m`: there CPython 3.11 exits by SIGINT itself, code -2, after a
    # KeyboardInterrupt that rosbags' exec of generated code let through was handled), in a process group of
    # its own signalled whole: what Ctrl-C in a terminal does (the worker process included).
    command = Path(sys.executable).parent / "orchard-map"
    # SIGINT back to its default in the child: a suite started in the background (nohup, `cmd &` in a script)
    # hands its children SIGINT ignored, and Python then never turns it into KeyboardInterrupt
    proc = subprocess.Popen([str(command), "run", str(BAGS / "front"), str(BAGS / "back"), "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        me = psutil.Process(proc.pid)
        deadline = time.monotonic() + 120
        while proc.poll() is None and time.monotonic() < deadline:
            if when == "reading the first side" and list(out.glob(".staging-*")):
                time.sleep(0.3)  # into the run: the staging folder holds its first files
                break
            if when == "as the trunk worker starts" and me.children():
                break  # the worker is importing: a Ctrl-C there printed its traceback
            time.sleep(0.02)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130, err
    assert "interrupted: nothing of this run was written to" in err and "Traceback" not in err, err
    assert _listing(out) == before and not list(out.glob(".staging-*"))
