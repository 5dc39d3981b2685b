"""io.results: atomic writers and validating readers of the result folder."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.errors import ResultFormatError
from orchard_mapping.io import results as R


def _tree(i: int, **kw: object) -> R.ResultTree:
    base: dict[str, object] = {
        "id": i,
        "position": (float(i), 0.5, 2.0),
        "trunk_diameter_m": 0.07,
        "height_m": 2.2,
        "canopy_volume_m3": 1.1,
        "fruit_count": 3,
        "fruit_positions": np.array([[0.1, 0.2, 0.3]]),
        "flags": ("trunk_occluded",),
    }
    base.update(kw)
    return R.ResultTree(**base)  # type: ignore[arg-type]


def test_trees_round_trip_json_and_csv(tmp_path: Path) -> None:
    trees = [_tree(0), _tree(1, trunk_diameter_m=None, fruit_count=None, fruit_positions=None, flags=())]
    dict_tree = {
        "id": 2,
        "position": np.array([2.0, 0.0, 1.0]),
        "trunk_diameter_m": np.float32(0.0625),
        "height_m": None,
        "canopy_volume_m3": None,
        "fruit_count": np.int64(4),
        "intervals": {"h": [2, 3]},
    }
    jp, cp = R.write_trees(tmp_path, [*trees, dict_tree])
    assert json.loads(jp.read_text())["schema"] == "orchard_mapping.result/1"
    back = R.read_trees(tmp_path)
    assert [t.id for t in back] == [0, 1, 2]
    assert back[0].position == (0.0, 0.5, 2.0) and back[0].flags == ("trunk_occluded",)
    np.testing.assert_allclose(back[0].fruit_positions, [[0.1, 0.2, 0.3]])
    assert back[1].trunk_diameter_m is None and back[1].fruit_positions is None
    assert back[2].fruit_count == 4 and back[2].extra == {"intervals": {"h": [2, 3]}}
    lines = cp.read_text().splitlines()
    base = "id,x_m,y_m,z_m,trunk_diameter_m,height_m,canopy_volume_m3,fruit_count,flags"
    assert lines[0] == ",".join([base, *R.TREES_CSV_MORE_COLUMNS])
    assert lines[2] == "1,1.0,0.5,2.0,,2.2,1.1,," + "," * len(R.TREES_CSV_MORE_COLUMNS)
    # a file of the base columns alone (older results) still reads
    old = tmp_path / "old.csv"
    old.write_text("\n".join([base, "1,1.0,0.5,2.0,,2.2,1.1,,"]) + "\n")
    assert R.read_trees_csv(old)[0].height_m == 2.2
    csv_back = R.read_trees_csv(cp)
    assert [(t.id, t.position, t.trunk_diameter_m, t.fruit_count, t.flags) for t in csv_back] == [
        (t.id, t.position, t.trunk_diameter_m, t.fruit_count, t.flags) for t in back
    ]


def test_trees_reader_names_file_and_field(tmp_path: Path) -> None:
    path = tmp_path / "trees.json"
    doc = {
        "schema": "orchard_mapping.result/1",
        "frame": "map",
        "trees": [{"id": 0, "position": [0, 0, 0]}, {"id": 1, "position": [0, 0]}],
    }
    path.write_text(json.dumps(doc))
    with pytest.raises(ResultFormatError, match=r"trees\.json: field 'trees\[1\]\.position'"):
        R.read_trees(path)
    doc["trees"][1] = {"id": 1}
    path.write_text(json.dumps(doc))
    with pytest.raises(ResultFormatError, match=r"'trees\[1\]\.position': missing"):
        R.read_trees(path)
    path.write_text(json.dumps({**doc, "schema": "other/2"}))
    with pytest.raises(ResultFormatError, match="field 'schema'"):
        R.read_trees(path)
    path.write_text("{not json")
    with pytest.raises(ResultFormatError, match="not valid JSON"):
        R.read_trees(path)
    with pytest.raises(ResultFormatError, match=r"field 'trees\[0\]\.height_m'"):
        R.write_trees(tmp_path / "x", [{"id": 0, "position": [0, 0, 0], "height_m": "tall"}])
    assert not (tmp_path / "x" / "trees.json").exists()


def test_tum_round_trip(tmp_path: Path) -> None:
    q = np.array([[0, 0, 0, 2.0], [0, 0, np.sin(0.1), np.cos(0.1)]])
    traj = StampedTrajectory(
        np.array([1700000000.123456, 1700000000.2]), np.array([[0, 0, 0], [1e-3, 2.5, -1]]), q, "odom_front"
    )
    path = R.write_tum(tmp_path / "trajectory_front.tum", traj)
    assert path.read_text().startswith("#")
    back = R.read_tum(path, "odom_front")
    np.testing.assert_array_equal(back.stamps, traj.stamps)
    np.testing.assert_array_equal(back.positions, traj.positions)
    np.testing.assert_allclose(back.quaternions, q / np.linalg.norm(q, axis=1, keepdims=True))


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1.0 0 0 0 0 0 0", "expected 8 numbers"),
        ("1.0 0 0 x 0 0 0 1", "not a number"),
        ("1.0 0 0 0 0 0 0 0", "zero quaternion"),
        ("0.5 0 0 0 0 0 0 1", "stamp 0.5 does not increase"),
        ("1.0 0 0 nan 0 0 0 1", "non-finite"),
    ],
)
def test_tum_malformed_line_names_file_and_line(tmp_path: Path, line: str, message: str) -> None:
    path = tmp_path / "trajectory_back.tum"
    path.write_text(f"# header\n0.9 0 0 0 0 0 0 1\n\n{line}\n")
    with pytest.raises(ResultFormatError, match=rf"trajectory_back\.tum:4: {message}"):
        R.read_tum(path)


def test_tum_empty_or_missing(tmp_path: Path) -> None:
    (tmp_path / "t.tum").write_text("# nothing\n")
    with pytest.raises(ResultFormatError, match="no poses"):
        R.read_tum(tmp_path / "t.tum")
    with pytest.raises(ResultFormatError, match="not found"):
        R.read_tum(tmp_path / "missing.tum")


def test_side_merge_and_timings_round_trip(tmp_path: Path) -> None:
    T = np.eye(4)
    T[:3, :3] = 1.05 * np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]])
    T[:3, 3] = [0.1, 2.0, -0.3]
    R.write_side_merge(tmp_path / "side_merge.json", T, residuals={"trunks_m": 0.01}, overlap=0.4)
    sm = R.read_side_merge(tmp_path)
    np.testing.assert_allclose(sm.T_front_back, T)
    assert sm.scale == pytest.approx(1.05) and sm.residuals == {"trunks_m": 0.01} and sm.overlap == 0.4
    doc = json.loads((tmp_path / "side_merge.json").read_text())
    doc["scale"] = 2.0
    (tmp_path / "side_merge.json").write_text(json.dumps(doc))
    with pytest.raises(ResultFormatError, match="field 'scale'"):
        R.read_side_merge(tmp_path)
    with pytest.raises(ResultFormatError, match="T_front_back"):
        R.write_side_merge(tmp_path / "bad.json", np.zeros((4, 4)))

    R.write_timings(tmp_path / "timings.json", {"odometry": 1.5, "merge": 0.25}, frames=10, recording_duration_s=2.0)
    tm = R.read_timings(tmp_path)
    assert dict(tm.stages) == {"odometry": 1.5, "merge": 0.25} and tm.total_s == 1.75 and tm.frames == 10
    assert tm.wall_s is None and tm.elapsed_s == 1.75  # a file without the wall clock: the stages' sum
    # stages that overlap (a worker process) sum to more than the wall clock, which the file then gives
    R.write_timings(tmp_path / "timings.json", {"odometry": 1.5, "trunks": 0.5}, recording_duration_s=2.0, wall_s=1.6)
    tm = R.read_timings(tmp_path)
    assert tm.total_s == 2.0 and tm.wall_s == 1.6 and tm.elapsed_s == 1.6 and dict(tm.merge_steps) == {}
    # the merge's steps: a breakdown of its stage, not more stages (the sum stays)
    R.write_timings(tmp_path / "timings.json", {"merge": 0.25}, merge_steps={"alignment": 0.125, "semantic_ba": 0.0625})
    tm = R.read_timings(tmp_path)
    assert dict(tm.merge_steps) == {"alignment": 0.125, "semantic_ba": 0.0625} and tm.total_s == 0.25
    (tmp_path / "timings.json").write_text(json.dumps({"stages": {"odometry": 1}, "wall_s": -2}))
    with pytest.raises(ResultFormatError, match=r"field 'wall_s'"):
        R.read_timings(tmp_path)
    (tmp_path / "timings.json").write_text(json.dumps({"stages": {"odometry": -1}}))
    with pytest.raises(ResultFormatError, match=r"field 'stages\.odometry'"):
        R.read_timings(tmp_path)
    (tmp_path / "timings.json").write_text(json.dumps({"stages": {}, "merge_steps": {"alignment": "1 s"}}))
    with pytest.raises(ResultFormatError, match=r"field 'merge_steps\.alignment'"):
        R.read_timings(tmp_path)


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_atomic_write_failure_keeps_previous_content(tmp_path: Path) -> None:
    target = tmp_path / "timings.json"
    R.atomic_write_json(target, {"stages": {"a": 1.0}})
    before = target.read_text()
    with pytest.raises(ResultFormatError, match="cannot serialise"):
        R.atomic_write_json(target, {"stages": {"a": object()}})
    with pytest.raises(ResultFormatError, match="cannot serialise"):
        R.atomic_write_json(target, {"stages": {"a": float("nan")}})
    assert target.read_text() == before
    with pytest.raises(ResultFormatError):
        R.atomic_write_json(tmp_path / "new.json", {"x": {1, 2}})
    assert not (tmp_path / "new.json").exists()
    assert _leftovers(tmp_path) == []


def test_atomic_write_failure_mid_write(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    target = tmp_path / "trees.csv"
    target.write_text("previous\n")

    def broken_fsync(fd: int) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "fsync", broken_fsync)
    with pytest.raises(OSError, match="disk full"):
        R.atomic_write_text(target, "new content that never lands\n")
    assert target.read_text() == "previous\n"
    assert _leftovers(tmp_path) == []


def test_trees_csv_carries_intervals_sides_and_fruit_counts(tmp_path: Path) -> None:
    t = R.ResultTree(3, (1.0, 2.0, 0.0), 0.07, 2.3, 0.5, 30, per_side={
        "front": {"trunk_id": 1, "diameter_m": 0.069, "height_m": 2.29}, "back": {"trunk_id": 4, "diameter_m": 0.071}},
        extra={"interval_90": {"height_m": [2.27, 2.33], "canopy_volume_m3": [0.44, 0.56]},
               "fruit_count_front": 21, "fruit_count_back": 18, "fruit_on_ground": 2, "clear_trunk_height_m": 0.6})
    _, cp = R.write_trees(tmp_path, [t])
    header, row = (line.split(",") for line in cp.read_text().splitlines())
    got = dict(zip(header, row, strict=True))
    assert (got["height_lo_m"], got["height_hi_m"]) == ("2.27", "2.33")
    assert got["trunk_diameter_lo_m"] == "" and got["canopy_volume_hi_m3"] == "0.56"
    assert (got["trunk_diameter_front_m"], got["trunk_diameter_back_m"]) == ("0.069", "0.071")
    assert (got["height_front_m"], got["height_back_m"]) == ("2.29", "")
    assert (got["fruit_count"], got["fruit_count_front"], got["fruit_count_back"], got["fruit_on_ground"]) == (
        "30", "21", "18", "2")
    assert got["clear_trunk_height_m"] == "0.6"
