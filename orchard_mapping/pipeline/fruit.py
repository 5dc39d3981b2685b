"""The fruit stage: each side's fruit as fusion reads its keyframes, then both sides' fruit once, per tree.

Per side (`FruitTap`, called by fusion with each keyframe's raw depth and colour, so no extra pass over the
bag): the keyframes fruit.every_m apart are segmented (core.fruit_pixels) and their fruit placed
(core.fruit.fruit_observations); when the side ends its fruit are linked (fruit_of_side) and travel in the
side map. After the merge (`measure_fruit`): the back side's fruit carried into map with its keyframes, both
sides associated (associate_sides), each fruit given the tree whose labelled points hold it, fruit lying on
the ground set apart.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree

from orchard_mapping.core.fruit import (
    FruitObservation,
    FruitParams,
    RowFruit,
    SideFruit,
    associate_sides,
    fruit_observations,
    fruit_of_side,
)
from orchard_mapping.core.geometry import keyframes_every, move_with_keyframes
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.io.bags import RGBDSequence
from orchard_mapping.io.results import ResultTree
from orchard_mapping.pipeline.sides import BagKeyframeImages

__all__ = ["FruitTap", "TreeFruit", "add_fruit", "fruit_points", "measure_fruit", "side_fruit_in_map", "FRUIT_ON_GROUND", "NO_TWO_SIDE_COUNT"]

log = logging.getLogger(__name__)

FRUIT_ON_GROUND = "fruit_on_ground"  # flag: fruit lying under the tree were left out of its count
NO_TWO_SIDE_COUNT = "no_two_side_fruit_count"  # flag: one side's fruit only (the other side missing or without)
# m: a fruit is its tree's when that tree's labelled points lie within its radius + this of its centre
FRUIT_TREE_MARGIN_M = 0.05


@lru_cache(maxsize=4)
def _pixel_model(path: str):
    from orchard_mapping.core.detection import resolve_model_path
    from orchard_mapping.core.fruit_pixels import load_model

    return load_model(resolve_model_path(path))


class FruitTap:
    """Fusion's view of a side's keyframes: the picked ones are searched for fruit (call with keyframe k, its
    depth (H, W) m and colour (H, W, 3)); `side_fruit()` links what was seen."""

    def __init__(self, side: str, stamps: np.ndarray, poses: np.ndarray, intr: CameraIntrinsics,
                 params: FruitParams) -> None:
        self.side, self.stamps, self.poses, self.intr, self.params = side, stamps, poses, intr, params
        self.picks = set(keyframes_every(poses, params.every_m))
        self.observations: list[FruitObservation] = []
        self.seconds = 0.0
        if params.source == "masks":
            from orchard_mapping.io.masks import MaskFolderDetector

            self._masks = MaskFolderDetector(params.masks_dir, side)
        else:
            self._model = _pixel_model(params.model)

    def _instances(self, k: int, color: np.ndarray) -> np.ndarray | None:
        if self.params.source == "masks":
            return self._masks.fruit_at(float(self.stamps[k]))
        from orchard_mapping.core.fruit_pixels import segment_fruit

        return segment_fruit(color, self._model).instances

    def __call__(self, k: int, depth: np.ndarray, color: np.ndarray) -> None:
        if k not in self.picks:
            return
        t0 = time.perf_counter()
        inst = self._instances(k, color)
        if inst is not None:
            self.observations += fruit_observations(inst, depth, self.poses[k], self.intr, self.params, keyframe=k)
        self.seconds += time.perf_counter() - t0

    def side_fruit(self) -> SideFruit:
        return fruit_of_side(self.side, self.observations, self.params)


def add_fruit(sm: SideMap, seq: RGBDSequence, params: FruitParams, labelled: bool = False) -> tuple[SideMap, float]:
    """The side map with its fruit found anew on its keyframes' images read from the side's bag `seq` (a side
    reconstructed without the fruit stage, or with other fruit settings), and the seconds it took."""
    index = np.searchsorted(seq.stamps, np.asarray(sm.keyframe_stamps) - 1e-6)  # (K,) each keyframe's frame
    tap = FruitTap(sm.side, sm.keyframe_stamps, sm.keyframe_poses, sm.intrinsics, params)
    k_of = {int(index[k]): k for k in tap.picks}
    t0 = time.perf_counter()
    for fi, depth, color in BagKeyframeImages(seq, sm.side, labelled).frames(sorted(k_of)):
        tap(k_of[fi], depth, color)
    return replace(sm, fruit=tap.side_fruit()), time.perf_counter() - t0


@dataclass(frozen=True)
class TreeFruit:
    """The row's fruit after the merge: each fruit once, with its tree."""

    row: RowFruit  # in map
    tree_id: np.ndarray  # (F,) int, the tree (trees.json id) each fruit hangs in, -1 none
    on_ground: np.ndarray  # (F,) bool: under a tree, on the ground (not counted)


FRUIT_POINT_MARGIN_M = 0.01  # m beyond a fruit's radius its points still are (the depth noise at 1.5 m)


def fruit_points(points: np.ndarray, row: RowFruit) -> np.ndarray:
    """(N,) bool: the points (N, 3) within a fruit's radius + FRUIT_POINT_MARGIN_M of its centre."""
    if not len(row.positions):
        return np.zeros(len(points), bool)
    d, k = cKDTree(row.positions).query(points, distance_upper_bound=0.5 * row.diameters_m.max() + FRUIT_POINT_MARGIN_M)
    hit = np.isfinite(d)
    hit[hit] = d[hit] <= 0.5 * row.diameters_m[k[hit]] + FRUIT_POINT_MARGIN_M
    return hit


def side_fruit_in_map(sm: SideMap, poses_map: np.ndarray) -> SideFruit:
    """The side's fruit carried into map with its keyframes (poses_map (K, 4, 4)), as its cloud is."""
    f = sm.fruit
    return replace(f, positions=move_with_keyframes(f.positions, sm.keyframe_poses, poses_map))


def measure_fruit(sides: dict[str, SideMap], poses: dict[str, np.ndarray], trees: list[ResultTree],
                  points: np.ndarray, point_tree: np.ndarray, grounds: np.ndarray, normals: np.ndarray,
                  params: FruitParams) -> tuple[list[ResultTree], TreeFruit | None]:
    """The trees with their fruit counted (front, back and both sides once), and the row's fruit. poses: each
    side's keyframes in map; points (N, 3) map with their tree ids (N,); per tree its local ground point and
    unit-up normal in map (T, 3). None (trees unchanged) when no side carries fruit."""
    have = {s: sm for s, sm in sides.items() if sm.fruit is not None}
    if not have:
        return trees, None
    empty = SideFruit("", np.zeros((0, 3)), np.zeros(0), np.zeros(0, int))
    f = side_fruit_in_map(have["front"], poses["front"]) if "front" in have else replace(empty, side="front")
    b = side_fruit_in_map(have["back"], poses["back"]) if "back" in have else replace(empty, side="back")
    row = associate_sides(f, b, params)
    ids = np.array([t.id for t in trees], int)
    tree_of = np.full(len(row.positions), -1, int)
    if len(row.positions) and len(points):
        labelled = point_tree >= 0
        lab = point_tree[labelled]
        near = cKDTree(points[labelled]).query_ball_point(row.positions, 0.5 * row.diameters_m + FRUIT_TREE_MARGIN_M)
        for i, idx in enumerate(near):  # the tree most of the points round the fruit belong to
            if idx:
                vals, counts = np.unique(lab[idx], return_counts=True)
                tree_of[i] = int(vals[np.argmax(counts)])
    # a fruit without a crown round it: its nearest trunk's tree, the ground test says if it lies there
    feet = np.array([t.position for t in trees], float).reshape(-1, 3)
    if len(feet):
        lost = tree_of < 0
        if lost.any():
            tree_of[lost] = ids[np.argmin(np.linalg.norm(row.positions[lost, None, :2] - feet[None, :, :2], axis=2),
                                          axis=1)]
    k_of = {tid: k for k, tid in enumerate(ids.tolist())}
    on_ground = np.zeros(len(row.positions), bool)
    for i, tid in enumerate(tree_of.tolist()):
        if tid in k_of:
            k = k_of[tid]
            h = float((row.positions[i] - grounds[k]) @ normals[k])
            on_ground[i] = h - 0.5 * row.diameters_m[i] < params.ground_margin_m
    one_side = not (len(f.positions) and len(b.positions))
    out = []
    for t in trees:
        mine = (tree_of == t.id) & ~on_ground
        seen = row.seen_from[mine]
        flags = list(t.flags)
        if np.any((tree_of == t.id) & on_ground):
            flags.append(FRUIT_ON_GROUND)
        if one_side:
            flags.append(NO_TWO_SIDE_COUNT)
        extra = {**t.extra,
                 "fruit_count_front": int(np.sum((seen == "front") | (seen == "both"))),
                 "fruit_count_back": int(np.sum((seen == "back") | (seen == "both"))),
                 "fruit_seen_from_both": int(np.sum(seen == "both")),
                 "fruit_on_ground": int(np.sum((tree_of == t.id) & on_ground)),
                 "fruit_diameters_m": [round(float(d), 4) for d in row.diameters_m[mine]]}
        out.append(replace(t, fruit_count=int(mine.sum()), fruit_positions=row.positions[mine],
                           flags=tuple(dict.fromkeys(flags)), extra=extra))
    log.info("fruit: %d in the row (%d seen from both sides), %d on the ground", int((~on_ground).sum()),
             int(np.sum(row.seen_from == "both")), int(on_ground.sum()))
    return out, TreeFruit(row, tree_of, on_ground)
