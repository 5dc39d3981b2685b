"""The two sides merged: initial alignment, initial transform and semantic bundle adjustment (`merge_sides`),
the clouds carried into map, and the trees (`two_side_trees`, `merge_to_trees`)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

import numpy as np

from orchard_mapping.config import OrchardConfig
from orchard_mapping.core.alignment import align_sides, icp_merge, pair_trunks
from orchard_mapping.core.alignment_types import AlignmentSide, SideAlignment
from orchard_mapping.core.geometry import SlabIndex, move_with_keyframes, rotation_angle_deg
from orchard_mapping.core.merge import HeightPrior, InitialTransform, SemanticPair, initial_transform
from orchard_mapping.core.posts import post_shapes
from orchard_mapping.core.semantic_ba import HeightAnchor, SemanticBAResult, SideShapes, semantic_bundle_adjust
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.core.trees import (
    foot_from_feet,
    foot_on_shared_axis,
    ground_kind,
    merge_axis,
    one_sided_outliers,
    opposite_one_sided_pairs,
    other_sides_post,
    row_direction,
    trunk_shapes,
    two_side_ground,
)
from orchard_mapping.core.trunks import TrunkLandmark, side_up_direction
from orchard_mapping.errors import AlignmentError
from orchard_mapping.io.results import ResultTree
from orchard_mapping.pipeline.trunks import DETECTOR_UNAVAILABLE, BandPair, TrunkWorker, two_side_diameter

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MergeOutcome:
    method: str  # merge.method that made it
    T_front_back: np.ndarray  # (4, 4) rigid odom_front <- odom_back
    pairs: tuple[tuple[int, int], ...]  # (front trunk id, back trunk id)
    alignment: SideAlignment | None  # None for the ICP baseline
    initial: InitialTransform | None
    sba: SemanticBAResult | None  # only with merge.method "semantic_ba"
    shapes: tuple[SideShapes, SideShapes] | None  # what the semantic BA measured of each side
    seconds: dict[str, float]  # per step: alignment, initial_transform, semantic_ba (or icp)


# MergeOutcome.method of a merge made without enough trunk pairs (alignment.fallback): the front views and each
# side's trunk line alone; every tree of it carries the flag MERGED_BY_GLOBAL_FEATURES
GLOBAL_FEATURES = "global_features"


MERGED_BY_GLOBAL_FEATURES = "merged_by_global_features"

# deg: the most the initial transform from the trunk pairs may turn the back side from the global features'
# alignment. That alignment faces the sides at each other to within a few degrees (its error: 0.6-4.3 deg on the
# simulator's 10-tree dense, standard and wind rows, 2.0-6.5 deg on the scanned-pine rows); the pairs then
# correct it by 0.5-5 deg. Two pairs of which one joins two different trees can turn the back side round: a
# hand-held scanned-pine row (seed 3, run seed 1) merged 170 deg off, the global features alone 6.5 deg.
MAX_TURN_FROM_ALIGNMENT_DEG = 30.0


def merge_sides(front: SideMap, back: SideMap, cfg: OrchardConfig) -> MergeOutcome:
    """Initial alignment (global features), the initial transform (paired trunks and grounds), then the
    semantic bundle adjustment of both sides (merge.method)."""
    def side_input(sm: SideMap) -> AlignmentSide:
        t = sm.trunks
        return AlignmentSide(sm.cloud_points, sm.keyframe_poses, np.array([x.base for x in t]).reshape(-1, 3),
                             np.array([merge_axis(x) for x in t]).reshape(-1, 3), np.array([x.id for x in t], int),
                             sm.scale_free, np.array([np.nan if x.diameter_m is None else x.diameter_m for x in t]))

    if np.array_equal(front.keyframe_stamps, back.keyframe_stamps):
        raise AlignmentError("the two sides are one recording (the same keyframe stamps): a merge needs one "
                             "recording of each side of the row")
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    fa, ba = side_input(front), side_input(back)
    if cfg.merge.method == "icp":
        T = icp_merge(fa, ba, cfg.alignment, rng)
        pairs_icp = pair_trunks(fa, ba, T, cfg.alignment.pair_radius_m)
        return MergeOutcome("icp", T, pairs_icp, None, None, None, None, {"icp": time.perf_counter() - t0})
    al = align_sides(fa, ba, cfg.alignment, rng)
    seconds = {"alignment": time.perf_counter() - t0}
    # Too few trunks seen from both sides: the global features alone (flagged). When the fallback was taken because
    # the candidate pairs disagreed and its own alignment pairs min_pairs trunks, those pairs go on to the initial
    # transform and the semantic BA as usual (the steady scanned-tree row: 5.3 deg / 106 mm -> 1.0 deg / 38 mm).
    if al.method == "trunk_lines" and len(al.pairs) < max(2, cfg.alignment.min_pairs):
        return MergeOutcome(GLOBAL_FEATURES, al.T_front_back, al.pairs, al, None, None, None, seconds)
    by_f = {t.id: t for t in front.trunks}
    by_b = {t.id: t for t in back.trunks}
    pairs = []
    for i, j in al.pairs:
        f, b = by_f[i], by_b[j]
        both = f.ground is not None and b.ground is not None
        pairs.append(SemanticPair(i, j, merge_axis(f), f.base, merge_axis(b), b.base,
                                  (f.ground.normal, f.ground.point) if both else None,
                                  (b.ground.normal, b.ground.point) if both else None,
                                  (f.ground.support_offset_m, b.ground.support_offset_m) if both else (0.0, 0.0)))
    prior = None
    if cfg.merge.sigma_alignment_height_m > 0:
        c_b = np.mean([p.origin_b for p in pairs], axis=0)  # (3,) the paired back trunks' centre
        prior = HeightPrior(al.front.T_canon_odom[1, :3], c_b, al.T_front_back[:3, :3] @ c_b + al.T_front_back[:3, 3])
    t0 = time.perf_counter()
    it = initial_transform(pairs, cfg.merge, prior)
    seconds["initial_transform"] = time.perf_counter() - t0
    turn = rotation_angle_deg(al.T_front_back[:3, :3].T @ it.T_front_back[:3, :3])
    if turn > MAX_TURN_FROM_ALIGNMENT_DEG:
        log.warning("the trunk pairs %s turn the back side %.0f deg from where the global features put it (at most "
                    "%.0f): a pair of two different trees; merged from the global features, every tree flagged %s",
                    list(al.pairs), turn, MAX_TURN_FROM_ALIGNMENT_DEG, MERGED_BY_GLOBAL_FEATURES)
        return MergeOutcome(GLOBAL_FEATURES, al.T_front_back, al.pairs, al, None, None, None, seconds)
    sba = shapes = None
    if cfg.merge.method == "semantic_ba":
        t0 = time.perf_counter()
        h = cfg.trunks.diameter_height_m
        back_poses = it.T_front_back[None] @ back.keyframe_poses
        posts = post_shapes([(front.posts, front.keyframe_poses), (back.posts, back_poses)])
        row = row_direction(np.array([by_f[i].base for i, _ in al.pairs]))  # map = odom_front
        shapes = (SideShapes(front.keyframe_poses, trunk_shapes(front, [i for i, _ in al.pairs], np.eye(4), h, row),
                             posts[0]),
                  SideShapes(back_poses, trunk_shapes(back, [j for _, j in al.pairs], it.T_front_back, h, row),
                             posts[1]))
        anchor = None
        if prior is not None and cfg.semantic_ba.height_sigma_m > 0:  # the initial transform's height prior
            point = it.T_front_back[:3, :3] @ prior.point_b + it.T_front_back[:3, 3]
            anchor = HeightAnchor(prior.up, point, float(prior.up @ prior.target_f), cfg.semantic_ba.height_sigma_m)
        sba = semantic_bundle_adjust(*shapes, cfg.semantic_ba, anchor)
        seconds["semantic_ba"] = time.perf_counter() - t0
    return MergeOutcome(cfg.merge.method, it.T_front_back, al.pairs, al, it, sba, shapes, seconds)


def map_poses(m: MergeOutcome, sides: dict[str, SideMap]) -> dict[str, np.ndarray]:
    """side -> (K, 4, 4) T_map_cam of its keyframes after the merge (the semantic BA's when it ran)."""
    if m.sba is not None:
        return {"front": m.sba.front_poses, "back": m.sba.back_poses}
    return {"front": sides["front"].keyframe_poses, "back": m.T_front_back[None] @ sides["back"].keyframe_poses}


def clouds_in_map(m: MergeOutcome, sides: dict[str, SideMap]) -> dict[str, np.ndarray]:
    """side -> (P, 3) its fused cloud in map, carried along with its keyframes by the merge."""
    return {side: move_with_keyframes(sides[side].cloud_points, sides[side].keyframe_poses, P)
            for side, P in map_poses(m, sides).items()}


def ray_in_map(point: np.ndarray, direction: np.ndarray, sm: SideMap, poses_map: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """A landmark's point (3,) and unit direction (3,) in its side's odom frame (a trunk's base and axis, a
    local ground's point and normal) carried into map as its cloud is (clouds_in_map): with the keyframe
    nearest the point. poses_map: map_poses(m, sides)[side]."""
    p = np.asarray(point, float)
    base, tip = move_with_keyframes(np.array([p, p + np.asarray(direction, float)]), sm.keyframe_poses, poses_map)
    return base, (tip - base) / np.linalg.norm(tip - base)


def tree_of_trunk(trees: list[ResultTree]) -> dict[tuple[str, int], int]:
    """(side, trunk id) -> the id of the tree that trunk belongs to after the merge."""
    return {(side, own["trunk_id"]): t.id for t in trees for side, own in (t.per_side or {}).items()}


OFF_ROW_LINE = "off_row_line"  # a one-sided trunk far across the row's line: not this row's tree
LOCAL_GROUND_NORMAL = "local_ground_normal"  # trees.json: unit up normal (map) of the local ground both sides fitted
PAIRED_AFTER_MERGE = "paired_after_merge"  # one tree from a front-only and a back-only trunk at one place


def two_side_trees(m: MergeOutcome, sides: dict[str, SideMap], cfg: OrchardConfig,
                   clouds: dict[str, np.ndarray] | None = None, worker: "TrunkWorker | None" = None
                   ) -> list[ResultTree]:
    """Every trunk of either side as a tree in map: paired ones with the two-side diameter of eq.
    objectCylinderFB (one radius from both sides' band points and views) and the foot on the local
    ground fitted to both sides' points, the others flagged one-sided. clouds: clouds_in_map(m, sides).
    worker: fits every other tree's two-side diameter meanwhile (the other core is idle in the merge)."""
    tp = cfg.trunks
    if clouds is None and m.sba is not None:
        clouds = clouds_in_map(m, sides)
    near = {side: SlabIndex(P) for side, P in clouds.items()} if clouds is not None else {}
    by = {side: {t.id: t for t in sides[side].trunks} for side in ("front", "back")}
    T_fb = m.T_front_back
    intr = sides["front"].intrinsics
    worker = worker if worker is not None and worker.spawned else None
    # each tree's draws from a generator of its own, so that it does not matter which process fits it
    band_pairs = {k: BandPair([(f.band_points, f.band_normals, f.band_views, f.band.cylinder),
                               (b.band_points, b.band_normals, b.band_views, b.band.cylinder)], intr, tp,
                              (cfg.seed, k, 1))
                  for k, (f, b) in enumerate((by["front"][i], by["back"][j]) for i, j in m.pairs)
                  if f.band is not None and b.band is not None}
    elsewhere = {k: worker.submit(two_side_diameter, job) for n, (k, job) in enumerate(band_pairs.items())
                 if n % 2} if worker is not None else {}
    if worker is not None:
        worker.start()
    trees: list[ResultTree] = []
    paired = {"front": set(), "back": set()}
    for k, (i, j) in enumerate(m.pairs):
        f, b = by["front"][i], by["back"][j]
        paired["front"].add(i)
        paired["back"].add(j)
        rng = np.random.default_rng((cfg.seed, k))
        ground_normal = None
        if m.sba is not None and m.shapes is not None:
            # The shared trunk after the semantic BA, down its axis to the ground: each side's base placed
            # by that side's adjusted camera, the foot on the best ground either side has (foot_on_shared_axis).
            Tt = m.sba.trunks_map[k]
            z = Tt[:3, 2]
            heights = []
            for shapes, poses, lm in ((m.shapes[0], m.sba.front_poses, f), (m.shapes[1], m.sba.back_poses, b)):
                sh = shapes.trunk(k)
                Ts = poses[sh.keyframe] @ sh.T_cam_trunk
                base_map = Ts[:3, 3] - tp.diameter_height_m * Ts[:3, 2]
                heights.append((ground_kind(lm), float((base_map - Tt[:3, 3]) @ z)))
            pos = foot_on_shared_axis(Tt, heights)
            r = max([t.diameter_m for t in (f, b) if t.diameter_m is not None] or [0.1]) / 2  # m; 0.1: a typical trunk
            shared = two_side_ground(near, Tt, pos, r, cfg.ground, rng)
            if shared is not None:
                pos = shared.point
                ground_normal = shared.normal if shared.normal @ z > 0 else -shared.normal
        else:  # the feet on the best ground either side has (as above), each side's carried into map
            feet = [(ground_kind(f), f.base), (ground_kind(b), T_fb[:3, :3] @ b.base + T_fb[:3, 3])]
            pos = foot_from_feet(feet)
        diameter, flags = None, []
        if k in band_pairs:
            diameter = (worker.result(elsewhere[k], two_side_diameter, band_pairs[k]) if k in elsewhere
                        else two_side_diameter(band_pairs[k]))
            if diameter is None:
                flags.append("two_side_fit_failed")
        if diameter is None:
            one = [t.diameter_m for t in (f, b) if t.diameter_m is not None]
            diameter = float(np.mean(one)) if one else None
            if not one:
                flags.append("trunk_hidden_at_diameter_height")
        # the plane both sides' points pin (two_side_ground): the tree's height is measured along its normal
        extra = {} if ground_normal is None else {LOCAL_GROUND_NORMAL: [round(float(v), 6) for v in ground_normal]}
        trees.append(ResultTree(len(trees), tuple(float(v) for v in pos), diameter, per_side={
            "front": {"trunk_id": i, "diameter_m": f.diameter_m},
            "back": {"trunk_id": j, "diameter_m": b.diameter_m}}, flags=tuple(flags) + _carried_flags(f, b),
            extra=extra))
    for side, T in (("front", np.eye(4)), ("back", T_fb)):
        for t in sides[side].trunks:
            if t.id in paired[side]:
                continue
            pos = T[:3, :3] @ t.base + T[:3, 3]
            trees.append(ResultTree(len(trees), tuple(float(v) for v in pos), t.diameter_m,
                                    per_side={side: {"trunk_id": t.id, "diameter_m": t.diameter_m}},
                                    flags=(f"seen_from_{side}_only",) + _carried_flags(t)))
    return trees


def _carried_flags(*trunks: TrunkLandmark) -> tuple[str, ...]:
    """The trunk flags a tree carries: the detector was down near it on some side (a tree there may be
    missing, or seen from one side only because of it)."""
    return (DETECTOR_UNAVAILABLE,) if any(DETECTOR_UNAVAILABLE in t.flags for t in trunks) else ()


def _set_aside_one_sided(trees: list[ResultTree], merged: MergeOutcome, sides: dict[str, SideMap]
                        ) -> list[ResultTree]:
    """The trees less the one-sided ones that repeat a tree both sides saw (core.trees.one_sided_outliers),
    and with OFF_ROW_LINE flagged on one-sided ones off the row's line (the traits stage leaves them out)."""
    if len(trees) < 2:
        return trees
    poses = map_poses(merged, sides)
    up = side_up_direction(np.concatenate(list(poses.values())))
    trees = _posts_of_the_other_side_out(trees, sides, poses, up)
    if len(trees) < 2:
        return trees
    two = np.array([len(t.per_side or {}) == 2 for t in trees])
    dup, off = one_sided_outliers(np.array([t.position for t in trees]), two, up)
    out = []
    for t, d, o in zip(trees, dup.tolist(), off.tolist(), strict=True):
        if d >= 0:
            log.warning("tree %d, seen from %s only, stands where tree %d does (both sides saw it): the same "
                        "tree, left out", t.id, next(iter(t.per_side or {"one side": 0})), trees[d].id)
            continue
        out.append(replace(t, flags=t.flags + (OFF_ROW_LINE,)) if o else t)
    # ids stay those of two_side_trees' list: the side merger's and the reporter's messages name them
    return join_opposite_one_sided(out, up)


def side_posts_in_map(sides: dict[str, SideMap], poses: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each side's post places (P, 3), carried into map with its keyframes (poses: map_poses), as its cloud is."""
    return {side: move_with_keyframes(np.array([p.place for p in sm.posts]).reshape(-1, 3), sm.keyframe_poses,
                                      poses[side]) for side, sm in sides.items()}


def _posts_of_the_other_side_out(trees: list[ResultTree], sides: dict[str, SideMap], poses: dict[str, np.ndarray],
                                 up: np.ndarray) -> list[ResultTree]:
    """The trees less the one-sided ones that are a post the other side modelled, by the frames of both sides:
    a trunk seen from one side only, where the other side saw a post, is that post when the frames that called
    the object a post (the other side's post views and those of its own side, TrunkLandmark.post_frames) are at
    least those that called it a trunk, a tie going to the post as within a side
    (core.posts.separate_trunks_from_posts). Dense row seed 41: a row-end post was a trunk in 18 front frames,
    a post in 12 front and 13 back ones; as a tree it took 80 % of its neighbour's crown."""
    places = side_posts_in_map(sides, poses)
    posts = {side: [(q, p.radius_m, len(p.observations)) for q, p in zip(places[side], sm.posts, strict=True)]
             for side, sm in sides.items()}
    out = []
    for t in trees:
        lm = None
        if len(t.per_side or {}) == 1:
            side, own = next(iter(t.per_side.items()))
            other = "back" if side == "front" else "front"
            lm = next((x for x in sides[side].trunks if x.id == own["trunk_id"]), None)
        frames = None if lm is None else other_sides_post(
            np.asarray(t.position), (t.trunk_diameter_m or 0.0) / 2, len(lm.observations), lm.post_frames,
            posts[other], up)
        if frames is None:
            out.append(t)
            continue
        log.warning("tree %d, a trunk seen from the %s side only (a trunk in %d frames, a post in %d), is the post "
                    "the %s side saw (%d frames): a post, left out", t.id, side, len(lm.observations),
                    lm.post_frames, other, frames)
    return out


def join_opposite_one_sided(trees: list[ResultTree], up: np.ndarray) -> list[ResultTree]:
    """A tree seen from the front only and one seen from the back only at one place (core.trees.
    opposite_one_sided_pairs) are one tree whose trunks the pairing missed: one tree with both sides' trunks, its
    foot the lower of the two (a side that saw the ground saw it lowest), its diameter their mean, flagged
    PAIRED_AFTER_MERGE (no two-side fit)."""
    one = {side: [k for k, t in enumerate(trees) if set(t.per_side or {}) == {side}] for side in ("front", "back")}
    pairs = opposite_one_sided_pairs(np.array([trees[k].position for k in one["front"]]).reshape(-1, 3),
                                     np.array([trees[k].position for k in one["back"]]).reshape(-1, 3), up)
    if not pairs:
        return trees
    unit_up = np.asarray(up, float) / np.linalg.norm(up)
    joined: dict[int, ResultTree] = {}
    gone: set[int] = set()
    for i, j in pairs:
        f, b = one["front"][i], one["back"][j]
        tf, tb = trees[f], trees[b]
        foot = min((tf.position, tb.position), key=lambda p: float(np.asarray(p) @ unit_up))
        dia = [x for x in (tf.trunk_diameter_m, tb.trunk_diameter_m) if x is not None]
        flags = tuple(x for x in tf.flags + tb.flags if not x.startswith("seen_from_")) + (PAIRED_AFTER_MERGE,)
        joined[f] = replace(tf, position=tuple(float(v) for v in foot),
                            trunk_diameter_m=float(np.mean(dia)) if dia else None,
                            per_side={**(tf.per_side or {}), **(tb.per_side or {})},
                            flags=tuple(dict.fromkeys(flags)))
        gone.add(b)
        log.warning("trees %d (front only) and %d (back only) stand at one place: one tree, its trunks paired "
                    "after the merge", tf.id, tb.id)
    return [joined.get(k, t) for k, t in enumerate(trees) if k not in gone]


def merge_to_trees(sides: dict[str, SideMap], cfg: OrchardConfig, worker: "TrunkWorker | None" = None
                   ) -> tuple[MergeOutcome, dict[str, np.ndarray], list[ResultTree]]:
    """The two sides merged (merge_sides), their clouds carried into map, and the trees: what `run` and the
    side merger node write. AlignmentError (MergeRefusedError's base) when the merge is refused. worker:
    fits half the trees' two-side diameters (two_side_trees)."""
    merged = merge_sides(sides["front"], sides["back"], cfg)
    clouds = clouds_in_map(merged, sides)
    trees = _set_aside_one_sided(two_side_trees(merged, sides, cfg, clouds, worker), merged, sides)
    if merged.method == GLOBAL_FEATURES:
        log.warning("too few trunks seen from both sides for the semantic merge: the sides were merged from the "
                    "global features alone (front views, each side's trunk line; error up to a trunk's width), "
                    "every tree is flagged %s", MERGED_BY_GLOBAL_FEATURES)
        trees = [replace(t, flags=t.flags + (MERGED_BY_GLOBAL_FEATURES,)) for t in trees]
    log.info("sides merged (%s) on %d trunk pairs%s", merged.method, len(merged.pairs),
             ": " + "; ".join(merged.alignment.log) if merged.alignment is not None else "")
    return merged, clouds, trees
