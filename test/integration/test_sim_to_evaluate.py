"""End to end through the CLI: simulate a row, read its bags back, evaluate a truth-derived result.

The result is built from the ground truth (as a perfect pipeline would write it), then perturbed:
the evaluator must report ~0 for the perfect one and the planted errors for the perturbed one.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from orchard_mapping.cli.main import app
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.io.bags import read_rgbd
from orchard_mapping.io.results import write_side_merge, write_trees, write_tum

runner = CliRunner()


@pytest.fixture(scope="module")
def sim_dir(scratch) -> Iterator[Path]:
    with scratch("sim") as root:
        out = root / "row"
        res = runner.invoke(app, ["simulate", "--scenario", "standard", "--trees", "3", "--seed", "3", "--out",
                                  str(out), "--set", "camera.rate_hz=2", "--set", "masks_every=0"])
        assert res.exit_code == 0, res.output
        yield out


def _perfect_result(truth: dict, out: Path, *, diam_mm: float = 0.0, height_cm: float = 0.0,
                    drift_per_m: float = 0.0) -> None:
    T_front_world = np.linalg.inv(np.array(truth["sides"]["front"]["T_world_odom"]))
    trees = []
    for t in truth["trees"]:
        p = T_front_world[:3, :3] @ np.array(t["position"]) + T_front_world[:3, 3]
        trees.append({"id": t["id"], "position": p.tolist(),
                      "trunk_diameter_m": t["trunk"]["diameter_m"] + diam_mm / 1000,
                      "height_m": t["height_m"] + height_cm / 100, "canopy_volume_m3": t["canopy_volume_m3"],
                      "fruit_count": t["fruit_visible"]["either"]})
    write_trees(out, trees)
    for side, s in truth["sides"].items():
        traj = np.array(s["trajectory"])
        pos = traj[:, 1:4].copy()
        # Planted drift: error growing linearly with distance travelled, along x of the odom frame.
        travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pos, axis=0), axis=1))])
        pos[:, 0] += drift_per_m * travelled
        write_tum(out / f"trajectory_{side}.tum", StampedTrajectory(traj[:, 0], pos, traj[:, 4:8], s["frame"]))
    write_side_merge(out / "side_merge.json", np.array(truth["T_front_back"]))


def test_bags_read_back_match_truth(sim_dir):
    truth = json.loads((sim_dir / "ground_truth.json").read_text())
    for side in ("front", "back"):
        seq = read_rgbd(sim_dir / side)
        stamps = np.array([p[0] for p in truth["sides"][side]["trajectory"]])
        assert len(seq) == len(stamps)
        np.testing.assert_allclose(seq.stamps, stamps, atol=1e-6)
        k = seq.intrinsics
        assert (k.width, k.height, k.fx) == (truth["camera"]["width"], truth["camera"]["height"], truth["camera"]["fx"])


def test_perfect_result_scores_zero_and_perturbed_result_moves(sim_dir, tmp_path):
    truth = json.loads((sim_dir / "ground_truth.json").read_text())
    perfect, bad = tmp_path / "perfect", tmp_path / "bad"
    perfect.mkdir()
    bad.mkdir()
    _perfect_result(truth, perfect)
    _perfect_result(truth, bad, diam_mm=4.0, height_cm=-7.0, drift_per_m=0.01)

    def metrics(result: Path) -> dict:
        res = runner.invoke(app, ["evaluate", "--truth", str(sim_dir / "ground_truth.json"),
                                  "--result", str(result), "--json"])
        assert res.exit_code == 0, res.output
        return json.loads(res.stdout)

    m0, m1 = metrics(perfect), metrics(bad)
    assert m0["matching"]["matched"] == 3 and m0["matching"]["missed"] == 0
    for side in ("front", "back"):
        assert m0["sides"][side]["drift_percent"] < 1e-3
        assert m0["sides"][side]["ate_percent"] < 1e-3
        # 1 cm per metre of path along one axis: the last pose is 1 % of the path off.
        assert m1["sides"][side]["drift_percent"] == pytest.approx(1.0, rel=0.02)
        assert 0 < m1["sides"][side]["ate_percent"] < m1["sides"][side]["drift_percent"]
    assert m0["traits"]["trunk_diameter_mae_mm"] < 1e-6
    assert m1["traits"]["trunk_diameter_mae_mm"] == pytest.approx(4.0, abs=1e-6)
    assert m1["traits"]["height_mae_cm"] == pytest.approx(7.0, abs=1e-6)
    assert m0["merge"]["rotation_error_deg"] < 1e-6
    assert m0["fruit_count"]["error_visible_percent"] == pytest.approx(0.0, abs=1e-9)


def test_cli_errors_are_typed_and_clear(tmp_path):
    res = runner.invoke(app, ["simulate", "--scenario", "no_such_row", "--out", str(tmp_path / "x")])
    assert res.exit_code == 2
    assert "unknown scenario 'no_such_row'" in res.output and "standard" in res.output
    res = runner.invoke(app, ["simulate", "--set", "row.n_tres=3", "--out", str(tmp_path / "y")])
    assert res.exit_code == 2 and "row.n_tres" in res.output
    res = runner.invoke(app, ["evaluate", "--truth", str(tmp_path / "missing.json"), "--result", str(tmp_path)])
    assert res.exit_code == 2 and "missing.json" in res.output
    res = runner.invoke(app, ["inspect", str(tmp_path / "nothing")])
    assert res.exit_code == 2 and "does not exist" in res.output


def test_config_command_prints_effective_yaml(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("seed: 5\n")
    res = runner.invoke(app, ["config", "--config", str(f)])
    assert res.exit_code == 0
    assert "seed: 5" in res.stdout and "color: /camera/color/image_raw" in res.stdout
    f.write_text("sed: 5\n")
    res = runner.invoke(app, ["config", "--config", str(f)])
    assert res.exit_code == 2 and "unknown key 'sed'" in res.output


def test_inspect_prints_truth_table(sim_dir):
    res = runner.invoke(app, ["inspect", str(sim_dir)])
    assert res.exit_code == 0, res.output
    assert "Ground truth per tree" in res.output and "RGB-D frames read back" in res.output


def test_help_is_fast_and_lists_commands():
    # --help must not import the heavy stack (open3d, rosbags): run it in a fresh interpreter.
    code = "import sys; from orchard_mapping.cli.main import app; print(sorted(m for m in sys.modules if m.startswith(('open3d','rosbags','gtsam'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ}).stdout
    assert out.strip() == "[]"
