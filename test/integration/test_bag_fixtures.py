"""The committed fixture recordings in bags/ (bags/README.md), read as a real recording would be read.

Each fixture is a simulator run kept small (half resolution, a low frame rate, zstd chunks): the bags
and their ground truth. These tests check that
- every bag reads back through `read_rgbd` like a recording from a vehicle (intrinsics, stamps, side
  labels of the single-bag drive) and agrees with its own ground truth (frames, stamps, and the depth
  at the true trunks);
- each fixture is still what the command in bags/README.md produces: the command is run again into a
  temporary folder and the result compared, so a change to the simulator that changes the fixtures
  fails here until they are regenerated (with the README's commands).
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from orchard_mapping.cli.main import app
from orchard_mapping.eval.ground_truth import load_ground_truth
from orchard_mapping.io.bags import read_rgbd

BAGS = Path(__file__).resolve().parents[2] / "bags"
README = BAGS / "README.md"


def _commands() -> dict[str, list[str]]:
    """Fixture name -> the `orchard-map simulate` arguments in bags/README.md (one command per line)."""
    cmds = {}
    for line in README.read_text().splitlines():
        if line.startswith("orchard-map simulate "):
            args = shlex.split(line)[1:]
            out = Path(args[args.index("--out") + 1])
            cmds[out.name] = args
    return cmds


COMMANDS = _commands()


def _bags_of(fixture: Path) -> dict[str, Path]:
    """Bag label -> folder, as the ground truth names them (front/back, or one loop bag)."""
    raw = json.loads((fixture / "ground_truth.json").read_text())
    return {s["bag"]: fixture / s["bag"] for s in raw["sides"].values()}


def test_every_fixture_has_its_command_and_is_small():
    fixtures = sorted(p.name for p in BAGS.iterdir() if p.is_dir())
    assert fixtures and fixtures == sorted(COMMANDS), (fixtures, sorted(COMMANDS))
    total = sum(f.stat().st_size for f in BAGS.rglob("*") if f.is_file())
    assert total < 8e6, f"bags/ holds {total / 1e6:.1f} MB: fixtures must stay a few MB"
    for name in fixtures:
        assert "--compress" in COMMANDS[name], name  # MCAP with zstd chunks


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_fixture_reads_like_a_recording_and_agrees_with_its_truth(name):
    fixture = BAGS / name
    gt = load_ground_truth(fixture / "ground_truth.json")
    raw = json.loads((fixture / "ground_truth.json").read_text())
    cam, bag_of_side = raw["camera"], {side: s["bag"] for side, s in raw["sides"].items()}
    dh = gt.diameter_height_m
    residuals = []
    for label, bag in _bags_of(fixture).items():
        seq = read_rgbd(bag)
        intr = seq.intrinsics
        assert (intr.width, intr.height, intr.fx, intr.cx) == (cam["width"], cam["height"], cam["fx"], cam["cx"])
        sides = [side for side, b in bag_of_side.items() if b == label]
        single_bag = len(sides) > 1  # one drive round the row: the side topic labels the frames
        frames = list(seq)
        assert all(f.side in sides for f in frames) if single_bag else all(f.side == "" for f in frames)
        for side in sides:
            true = gt.sides[side]
            mine = [f for f in frames if not single_bag or f.side == side]
            assert len(mine) == len(true.trajectory.stamps), (name, side)
            np.testing.assert_allclose([f.stamp for f in mine], true.trajectory.stamps, atol=1e-6)
            T_world_cam = true.T_world_odom[None] @ _poses(true.trajectory)
            for f, T in zip(mine, T_world_cam, strict=True):
                assert f.depth is not None and f.color.shape == (intr.height, intr.width, 3)
                residuals += _trunk_depth_residuals(f.depth, T, gt, dh, intr)
    r = np.array(residuals)  # m: measured - expected depth at the trunk axis pixel, diameter height
    assert len(r) >= 5, f"{name}: trunks seen at the diameter height in only {len(r)} frames"
    # The sensor's depth sd is 0.004 z^2 (~6 mm at 1.25 m): the trunk pixels agree with the truth's trunks.
    assert np.median(np.abs(r)) < 0.01, (name, np.median(np.abs(r)))
    assert np.mean(np.abs(r) < 0.03) > 0.8, (name, np.mean(np.abs(r) < 0.03))


def _poses(traj) -> np.ndarray:
    from orchard_mapping.core.geometry import pose_matrices

    return pose_matrices(np.asarray(traj.positions), np.asarray(traj.quaternions))


def _trunk_depth_residuals(depth: np.ndarray, T_world_cam: np.ndarray, gt, dh: float, intr) -> list[float]:
    """Measured minus expected depth (m) at the pixel of each trunk's axis point at the diameter height."""
    out = []
    for tree in gt.trees:
        axis = tree.trunk_top - tree.trunk_base
        axis = axis / np.linalg.norm(axis)
        P = tree.position + axis * dh / axis[2]  # world, on the axis at the diameter height
        pc = (P - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]  # camera frame
        if pc[2] <= 0.2:
            continue
        u = intr.fx * pc[0] / pc[2] + intr.cx
        v = intr.fy * pc[1] / pc[2] + intr.cy
        if not (5 <= u < intr.width - 5 and 5 <= v < intr.height - 5):
            continue
        win = depth[int(round(v)) - 1:int(round(v)) + 2, int(round(u)) - 1:int(round(u)) + 2]
        if not (win > 0).all():
            continue
        # The ray through the axis point meets the trunk's near surface about one radius before the axis.
        expected = pc[2] * (1.0 - 0.5 * tree.diameter_m / np.linalg.norm(pc))
        out.append(float(np.median(win)) - expected)
    return out


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_fixture_is_what_its_readme_command_produces(name, tmp_path):
    args = COMMANDS[name]
    i = args.index("--out")
    fresh = tmp_path / name
    res = CliRunner().invoke(app, [*args[:i + 1], str(fresh), *args[i + 2:]])
    assert res.exit_code == 0, res.output
    old_truth = json.loads((BAGS / name / "ground_truth.json").read_text())
    new_truth = json.loads((fresh / "ground_truth.json").read_text())
    _assert_same_json(old_truth, new_truth, "ground_truth")
    for label, bag in _bags_of(BAGS / name).items():
        old_frames, new_frames = list(read_rgbd(bag)), list(read_rgbd(fresh / label))
        assert len(old_frames) == len(new_frames), (name, label)
        for a, b in zip(old_frames, new_frames, strict=True):
            assert a.stamp == pytest.approx(b.stamp, abs=1e-9) and a.side == b.side
            # Another processor may ray-cast an edge pixel differently: compare with a tolerance.
            dc = np.abs(a.color.astype(int) - b.color.astype(int))
            assert dc.mean() < 1.0 and np.mean(dc <= 2) > 0.98, (name, label, a.index, dc.mean())
            dd = np.abs(a.depth - b.depth)
            assert np.mean(dd <= 0.002) > 0.98, (name, label, a.index, np.mean(dd <= 0.002))


def _assert_same_json(a, b, where: str) -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and sorted(a) == sorted(b), where
        for k in a:
            _assert_same_json(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same_json(x, y, f"{where}[{i}]")
    elif isinstance(a, float) or isinstance(b, float):
        assert b == pytest.approx(a, rel=1e-6, abs=1e-6), where
    else:
        assert a == b, where


def test_inspect_counts_the_frames_of_each_side_in_the_single_bag_drive():
    fixture = BAGS / "loop_2trees"
    gt = load_ground_truth(fixture / "ground_truth.json")
    res = CliRunner().invoke(app, ["inspect", str(fixture / "loop")])
    assert res.exit_code == 0, res.output
    n = {side: len(gt.sides[side].trajectory.stamps) for side in ("front", "back")}
    assert n["front"] > 0 and n["back"] > 0
    assert f"back: {n['back']}, front: {n['front']}" in res.output, res.output
