"""pipeline.fruit.measure_fruit: both sides' fruit counted once per tree, fruit on the ground apart, flags."""

from __future__ import annotations

import numpy as np

from orchard_mapping.core.fruit import FruitParams, SideFruit
from orchard_mapping.core.sidemap import Observations, SideMap
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.io.results import ResultTree
from orchard_mapping.pipeline.fruit import FRUIT_ON_GROUND, NO_TWO_SIDE_COUNT, measure_fruit

INTR = CameraIntrinsics(640, 480, 615.0, 615.0, 319.5, 239.5)


def _side(name: str, fruit: SideFruit | None) -> SideMap:
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    poses[:, 0, 3] = [0.0, 1.0, 2.0]
    empty = Observations(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0))
    return SideMap(name, f"odom_{name}", INTR, np.arange(3.0), poses, np.zeros((0, 3)), empty, [],
                   np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8), fruit=fruit)


def _row():
    """Two trees at x = 0 and 1 m (z up); each crown a cloud of labelled points; fruit in each crown, some seen
    from both sides, two lying on the ground under tree 1."""
    rng = np.random.default_rng(2)
    crowns = [rng.normal([x, 0.0, 1.5], 0.2, (4000, 3)) for x in (0.0, 1.0)]
    points = np.concatenate(crowns)
    point_tree = np.repeat([10, 11], 4000)  # trees.json ids
    # fruit 10 cm apart in the middle of each crown (12 and 9), two on the ground under tree 1
    grid = np.stack(np.meshgrid([-0.1, 0.0, 0.1], [-0.05, 0.05], [1.4, 1.5]), -1).reshape(-1, 3)  # (12, 3)
    true = np.concatenate([grid, grid[:9] + [1.0, 0.0, 0.0], [[1.1, 0.1, 0.04], [0.9, -0.2, 0.05]]])
    front_i, back_i = np.r_[0:8, 12:18, 21], np.r_[4:12, 15:21, 22]
    noise = np.random.default_rng(3)

    def seen(i: np.ndarray, side: str) -> SideFruit:
        return SideFruit(side, true[i] + noise.normal(0, 0.003, (len(i), 3)), np.full(len(i), 0.075),
                         np.full(len(i), 4))
    return points, point_tree, seen(front_i, "front"), seen(back_i, "back")


TREES = [ResultTree(10, (0.0, 0.0, 0.0)), ResultTree(11, (1.0, 0.0, 0.0))]
UP = np.tile([0.0, 0.0, 1.0], (2, 1))  # each tree's local ground normal


def _measure(front: SideFruit | None, back: SideFruit | None, points: np.ndarray, point_tree: np.ndarray):
    sides = {"front": _side("front", front), "back": _side("back", back)}
    poses = {s: sm.keyframe_poses for s, sm in sides.items()}
    return measure_fruit(sides, poses, TREES, points, point_tree, np.array([t.position for t in TREES]), UP,
                         FruitParams())


def test_each_fruit_once_per_tree_and_the_ground_apart():
    points, point_tree, front, back = _row()
    out, fruit = _measure(front, back, points, point_tree)
    assert [t.fruit_count for t in out] == [12, 9]
    assert out[0].extra["fruit_count_front"] == 8 and out[0].extra["fruit_count_back"] == 8
    assert out[0].extra["fruit_seen_from_both"] == 4
    assert out[1].extra["fruit_count_front"] == 6 and out[1].extra["fruit_count_back"] == 6  # 15-17 seen from both
    assert out[1].extra["fruit_on_ground"] == 2 and FRUIT_ON_GROUND in out[1].flags
    assert FRUIT_ON_GROUND not in out[0].flags
    assert len(out[0].fruit_positions) == 12 and len(out[0].extra["fruit_diameters_m"]) == 12
    assert fruit is not None and fruit.on_ground.sum() == 2


def test_one_side_without_fruit_is_flagged_not_counted_twice():
    points, point_tree, front, _ = _row()
    out, _ = _measure(front, None, points, point_tree)
    assert [t.fruit_count for t in out] == [8, 6]
    assert all(NO_TWO_SIDE_COUNT in t.flags for t in out)
    # no side carries fruit: trees unchanged, no fruit result
    same, fr = _measure(None, None, points, point_tree)
    assert same == TREES and fr is None
