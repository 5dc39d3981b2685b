"""Tree traits in the merged map (paper: "Measuring Tree Morphology"): each tree's height and canopy volume
from the merged cloud, and every point of it labelled (tree, class) for trees.laz.

The merge gives each tree its foot in map and, through its trunks, the local ground planes each side fitted
(carried into map with their keyframes, as the cloud is); the posts each side modelled are cut out. The core
(core.traits.measure_row) works in a row frame: x along the row, z up the mean local ground normal; map is the
front camera's optical frame (y down), so the points go into that frame first and only labels and lengths
come back.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from orchard_mapping.config import OrchardConfig
from orchard_mapping.core.segmentation import row_axes
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.core.traits import KIND_GROUND, KIND_POST, KIND_TREE, KIND_WIRE, RowTraits, measure_row
from orchard_mapping.core.trees import row_direction
from orchard_mapping.core.trunks import TrunkLandmark, side_up_direction
from orchard_mapping.io.laz import CLASS, SIDE_CODE
from orchard_mapping.io.results import ResultTree
from orchard_mapping.pipeline.fruit import TreeFruit, fruit_points, measure_fruit
from orchard_mapping.pipeline.merge import (
    LOCAL_GROUND_NORMAL,
    OFF_ROW_LINE,
    MergeOutcome,
    map_poses,
    merge_to_trees,
    ray_in_map,
    side_posts_in_map,
)
from orchard_mapping.pipeline.trunks import TrunkWorker

__all__ = ["NO_CANOPY_POINTS", "SEGMENTATION_UNCERTAIN", "RowLabels", "merge_and_measure", "measure_trees"]

log = logging.getLogger(__name__)

# 90 % intervals: half-widths from the errors on five simulated 10-tree rows (standard 21 and 31, wind 32,
# slope_weeds 33, dense 41: the 90th percentile of |error|): trunk diameter 0.7 mm, canopy volume 12 %; the
# height's 2.5 cm is added in quadrature to the two sides' disagreement (the heights of each side's points
# alone), which with it covered 88 % of those trees' heights (a constant 2.5 cm: 86 %, 1.8 cm: 76 %). The
# diameter's 0.7 mm likewise to the two sides' own diameters' difference: on those rows and young 61, 92 % of
# the diameters covered (81 % without; half the difference: 85 %). They say how well the product does where it
# is at home; real data's errors are larger (docs/traits.md).
INTERVAL_HALF = {"trunk_diameter_m": ("m", 0.0007), "height_m": ("m", 0.025), "canopy_volume_m3": ("share", 0.12)}
# wider where the evidence is weaker: a tree seen from one side, a crown not split from its neighbour's, sides
# merged from global features alone (centimetres off, not millimetres)
INTERVAL_WIDEN = {"seen_from_front_only": 2.0, "seen_from_back_only": 2.0, "segmentation_uncertain": 2.0,
                  "merged_by_global_features": 3.0}
SEGMENTATION_UNCERTAIN = "segmentation_uncertain"  # a neighbour's canopy could not be split from this one's
NO_CANOPY_POINTS = "no_canopy_points"  # nothing of the tree above its clear trunk: no height, no volume
# m beyond the trunk radius a point of the tree below its clear trunk height still counts as trunk (the
# fused trunk surface scatters ~1 cm; the 3 cm also takes in the bark's relief)
TRUNK_MARGIN_M = 0.03


@dataclass(frozen=True)
class RowLabels:
    """Per point of the merged cloud (front side's points, then the back side's, as merged.ply holds them)."""

    points: np.ndarray  # (N, 3) m, map
    colors: np.ndarray  # (N, 3) uint8
    side: np.ndarray  # (N,) uint8, SIDE_CODE
    tree_id: np.ndarray  # (N,) int32, the tree's id in trees.json, -1 none
    classification: np.ndarray  # (N,) uint8, io.laz.CLASS
    R_row_map: np.ndarray = field(default_factory=lambda: np.eye(3))  # (3, 3) rows: the row frame's x, y, z in map
    fruit: TreeFruit | None = None  # the row's fruit, each once, with its tree (None: no fruit stage)
    recorded_s: float = 0.0  # s since the epoch: the recording's first keyframe (trees.laz's creation day)


def _tree_landmarks(trees: list[ResultTree], sides: dict[str, SideMap]) -> Iterator[tuple[int, str, TrunkLandmark]]:
    """(tree index, side, that side's trunk landmark) for every side trunk of every tree."""
    by = {side: {t.id: t for t in sm.trunks} for side, sm in sides.items()}
    for k, tree in enumerate(trees):
        for side, own in (tree.per_side or {}).items():
            lm = by.get(side, {}).get(own.get("trunk_id"))
            if lm is not None:
                yield k, side, lm


def _tree_grounds(trees: list[ResultTree], sides: dict[str, SideMap], poses: dict[str, np.ndarray],
                  up: np.ndarray) -> np.ndarray:
    """(T, 3) unit up normal of each tree's local ground in map: the plane fitted to both sides' points where the
    merge fitted one (LOCAL_GROUND_NORMAL), else the mean of the planes its sides fitted, carried into map; `up`
    where no side fitted one. Each side sees its half of the ground round the trunk, so its plane tilts freely
    about the row's line; the plane through both halves does not (slope_weeds 33: height MAE 3.6 -> see
    docs/traits.md)."""
    normals: list[list[np.ndarray]] = [
        [np.asarray(t.extra[LOCAL_GROUND_NORMAL], float)] if t.extra.get(LOCAL_GROUND_NORMAL) is not None else []
        for t in trees]
    two_side = [bool(ns) for ns in normals]
    for k, side, lm in _tree_landmarks(trees, sides):
        if lm.ground is not None and not two_side[k]:
            _, n = ray_in_map(lm.ground.point, lm.ground.normal, sides[side], poses[side])
            normals[k].append(n)
    out = np.tile(up, (len(trees), 1))
    for k, ns in enumerate(normals):
        if ns:
            n = np.mean([v if v @ up > 0 else -v for v in ns], axis=0)
            out[k] = n / np.linalg.norm(n)
    return out


# m above the foot where a tree's trunk axis gives the point its crown is split from its neighbours': the
# middle of a crown (0.6-2.5 m on the simulator's rows). Trees lean (up to 5 deg there): at the foot the cut
# between two crowns was 8-10 cm off on a 2-tree row (volumes -14 and +18 %).
SPLIT_HEIGHT_M = 1.2


def _split_points(trees: list[ResultTree], sides: dict[str, SideMap], poses: dict[str, np.ndarray],
                  feet: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(T, 3) map: each tree's trunk axis (the mean of its sides' axes, carried into map) SPLIT_HEIGHT_M
    above its foot; straight up the ground normal where no side has an axis."""
    axes: list[list[np.ndarray]] = [[] for _ in trees]
    for k, side, lm in _tree_landmarks(trees, sides):
        axis = lm.merge_axis if lm.merge_axis is not None else lm.axis
        _, a = ray_in_map(lm.base, axis, sides[side], poses[side])
        axes[k].append(a if a @ normals[k] > 0 else -a)
    out = feet + SPLIT_HEIGHT_M * normals
    for k, ax in enumerate(axes):
        if ax:
            a = np.mean(ax, axis=0)
            a /= np.linalg.norm(a)
            out[k] = feet[k] + a * SPLIT_HEIGHT_M / max(float(a @ normals[k]), 0.5)
    return out


def _posts_in_map(sides: dict[str, SideMap], poses: dict[str, np.ndarray]) -> tuple[np.ndarray, float]:
    """((P, 3) a point on each post's axis in map, the widest post radius m) of the posts both sides modelled."""
    radii = [p.radius_m for sm in sides.values() for p in sm.posts]
    return np.concatenate(list(side_posts_in_map(sides, poses).values())).reshape(-1, 3), float(max(radii, default=0.0))


def measure_trees(merged: MergeOutcome, sides: dict[str, SideMap], clouds: dict[str, np.ndarray],
                  trees: list[ResultTree], cfg: OrchardConfig) -> tuple[list[ResultTree], RowLabels]:
    """The trees with height and canopy volume filled in (flags where they could not be measured), and the
    merged cloud's per-point labels. clouds: each side's cloud in map (clouds_in_map)."""
    if any(OFF_ROW_LINE in t.flags for t in trees):  # not this row's trees: no cell of their own, no traits
        kept, labels = measure_trees(merged, sides, clouds, [t for t in trees if OFF_ROW_LINE not in t.flags], cfg)
        by_id = {t.id: t for t in kept}
        return [by_id.get(t.id, t) for t in trees], labels
    t0 = time.perf_counter()
    poses = map_poses(merged, sides)
    pts = np.concatenate([clouds["front"], clouds["back"]])  # (N, 3) map
    colors = np.concatenate([sides["front"].cloud_colors, sides["back"].cloud_colors])
    side = np.repeat([SIDE_CODE["front"], SIDE_CODE["back"]], [len(clouds["front"]), len(clouds["back"])])
    recorded_s = float(min(sm.keyframe_stamps[0] for sm in sides.values() if len(sm.keyframe_stamps)))
    none = RowLabels(pts, colors, side.astype(np.uint8), np.full(len(pts), -1, np.int32),
                     np.full(len(pts), CLASS["none"], np.uint8), recorded_s=recorded_s)
    if not trees or not len(pts):
        return trees, none
    up = side_up_direction(np.concatenate(list(poses.values())))  # both sides' cameras in map
    feet = np.array([t.position for t in trees], float)  # (T, 3) map
    normals = _tree_grounds(trees, sides, poses, up)
    # the row frame: x along the row (through the feet; the cameras' path for a row of one tree), z up
    if len(trees) > 1:
        along = row_direction(feet)
    else:
        cams = np.concatenate([P[:, :3, 3] for P in poses.values()])
        along = row_direction(cams)
    R = row_axes(along, up)  # (3, 3) rows: the row frame's axes in map
    origin = feet.mean(axis=0)

    def to_row(p: np.ndarray) -> np.ndarray:
        return (np.asarray(p, float) - origin) @ R.T

    post_places, post_radius = _posts_in_map(sides, poses)
    radius = np.array([(t.trunk_diameter_m or 0.0) / 2 for t in trees])  # (T,) m
    # the clear trunk from each tree's own points (canopy_base_height): its trunk landmark runs on up the leader
    result: RowTraits = measure_row(
        to_row(pts), to_row(_split_points(trees, sides, poses, feet, normals)), to_row(feet), normals @ R.T,
        np.full(len(trees), np.nan),
        np.array([1.0, 0.0, 0.0]), cfg.traits, post_points=to_row(post_places) if len(post_places) else None,
        post_radius_m=post_radius, trunk_radii=radius, point_sides=side)
    clear = np.array([m.clear_height_m if np.isfinite(m.clear_height_m) else 0.0 for m in result.trees])
    ids = np.array([t.id for t in trees])
    tree_id = np.where(result.tree >= 0, ids[np.maximum(result.tree, 0)], -1).astype(np.int32)
    cls = np.full(len(pts), CLASS["none"], np.uint8)
    cls[result.kind == KIND_GROUND] = CLASS["ground"]
    cls[result.kind == KIND_POST] = CLASS["post"]
    cls[result.kind == KIND_WIRE] = CLASS["wire"]
    tree_pts = result.kind == KIND_TREE
    cls[tree_pts] = CLASS["canopy"]
    # the trunk: a tree's points near its axis (the foot along its ground normal) below its clear trunk height
    k = np.maximum(result.tree, 0)
    d = pts - feet[k]  # (N, 3)
    h = np.sum(d * normals[k], axis=1)
    off = np.linalg.norm(d - h[:, None] * normals[k], axis=1)
    trunk = tree_pts & (h <= np.maximum(clear[k], 0.0)) & (off <= radius[k] + TRUNK_MARGIN_M)
    cls[trunk] = CLASS["trunk"]
    out = []
    for tree, m in zip(trees, result.trees, strict=True):
        flags = list(tree.flags)
        if not m.separated:
            flags.append(SEGMENTATION_UNCERTAIN)
        height = float(m.height_m) if np.isfinite(m.height_m) else None
        volume = float(m.canopy_volume_m3) if np.isfinite(m.canopy_volume_m3) and m.canopy_volume_m3 > 0 else None
        if height is None or volume is None:
            flags.append(NO_CANOPY_POINTS)
        extra = dict(tree.extra)
        if np.isfinite(m.clear_height_m):
            extra["clear_trunk_height_m"] = round(float(m.clear_height_m), 4)  # where its canopy begins
        flags = list(dict.fromkeys(flags))
        values = {"trunk_diameter_m": tree.trunk_diameter_m, "height_m": height, "canopy_volume_m3": volume}
        sides_h = dict(zip(("front", "back"), m.height_by_side, strict=True))
        spread = {"height_m": abs(sides_h["front"] - sides_h["back"])} if all(
            np.isfinite(v) for v in sides_h.values()) else {}
        sides_d = [v.get("diameter_m") for v in (tree.per_side or {}).values()]
        if len(sides_d) == 2 and None not in sides_d:
            spread["trunk_diameter_m"] = abs(float(sides_d[0]) - float(sides_d[1]))
        extra["interval_90"] = _intervals(values, flags, spread)
        per_side = {s: dict(v) for s, v in (tree.per_side or {}).items()}
        for s_name, hs in sides_h.items():
            if np.isfinite(hs):
                per_side.setdefault(s_name, {})["height_m"] = round(float(hs), 4)
        out.append(replace(tree, height_m=height, canopy_volume_m3=volume, flags=tuple(flags), extra=extra,
                           per_side=per_side or tree.per_side))
    log.info("traits: %d trees in %.2f s (%s)", len(trees), time.perf_counter() - t0, cfg.traits.segmentation)
    fruit = None
    if cfg.fruit.enabled:
        out, fruit = measure_fruit(sides, poses, out, pts, tree_id, feet, normals, cfg.fruit)
        if fruit is not None:
            cls[fruit_points(pts, fruit.row)] = CLASS["fruit"]
    return out, RowLabels(pts, colors, side.astype(np.uint8), tree_id, cls, R, fruit, recorded_s)


def _intervals(values: dict[str, float | None], flags: list[str], spread: dict[str, float]
               ) -> dict[str, list[float]]:
    """trait -> [low, high], the 90 % interval of each measured trait: INTERVAL_HALF, widened by the flags
    (INTERVAL_WIDEN), and by the two sides' disagreement where each side measured the trait (`spread`, in the
    trait's unit), added in quadrature."""
    widen = max([INTERVAL_WIDEN.get(f, 1.0) for f in flags], default=1.0)
    out = {}
    for trait, value in values.items():
        if value is None:
            continue
        unit, half = INTERVAL_HALF[trait]
        h = widen * float(np.hypot(half * (value if unit == "share" else 1.0), spread.get(trait, 0.0)))
        out[trait] = [round(value - h, 5), round(value + h, 5)]
    return out


def merge_and_measure(sides: dict[str, SideMap], cfg: OrchardConfig, worker: TrunkWorker | None = None
                      ) -> tuple[MergeOutcome, dict[str, np.ndarray], list[ResultTree], RowLabels, float]:
    """merge_to_trees, then each tree's traits: what `run` and the side merger node write. Also the traits
    stage's seconds. AlignmentError when the merge is refused."""
    merged, clouds, trees = merge_to_trees(sides, cfg, worker)
    t0 = time.perf_counter()
    trees, labels = measure_trees(merged, sides, clouds, trees, cfg)
    return merged, clouds, trees, labels, time.perf_counter() - t0
