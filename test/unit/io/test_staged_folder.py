"""io.results.staged_folder: a set of result files lands whole or not at all (`orchard-map run`, the side
merger node)."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.io.results import staged_folder


def test_the_files_move_in_only_when_the_block_succeeds(tmp_path):
    out = tmp_path / "a" / "b"
    with staged_folder(out) as stage:
        (stage / "x.json").write_text("1")
        assert not (out / "x.json").exists()  # not yet: the set is not complete
    assert (out / "x.json").read_text() == "1"
    assert [p.name for p in out.iterdir()] == ["x.json"]  # no staging folder left behind


def test_a_failed_block_keeps_the_earlier_set_and_removes_the_folders_it_made(tmp_path):
    out = tmp_path / "res"
    out.mkdir()
    (out / "x.json").write_text("old")
    with pytest.raises(RuntimeError), staged_folder(out) as stage:
        (stage / "x.json").write_text("new")
        raise RuntimeError("stopped half way")
    assert (out / "x.json").read_text() == "old" and [p.name for p in out.iterdir()] == ["x.json"]
    fresh = tmp_path / "new" / "deeper"
    with pytest.raises(KeyboardInterrupt), staged_folder(fresh):
        raise KeyboardInterrupt
    assert not (tmp_path / "new").exists()


def test_a_landmark_carried_into_map_moves_with_its_nearest_keyframe():
    from orchard_mapping.pipeline import ray_in_map

    class _Side:  # the one field ray_in_map reads of a SideMap
        keyframe_poses = np.stack([np.eye(4), np.eye(4)])
    _Side.keyframe_poses[1, :3, 3] = [10.0, 0, 0]
    after = _Side.keyframe_poses.copy()
    after[1, :3, :3] = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # the far keyframe turned 90 deg about z
    after[1, :3, 3] = [10.0, 0.5, 0]
    base, axis = ray_in_map(np.array([9.0, 0, 0]), np.array([1.0, 0, 0]), _Side, after)
    # nearest keyframe: the far one; its move is T_after T_before^-1
    assert np.allclose(base, [10.0, -0.5, 0.0]) and np.allclose(axis, [0.0, 1.0, 0.0])
    base, axis = ray_in_map(np.array([1.0, 0, 0]), np.array([0, 0, 2.0]), _Side, after)
    assert np.allclose(base, [1.0, 0, 0]) and np.allclose(axis, [0, 0, 1.0])
