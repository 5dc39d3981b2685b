"""Per-tree geometry of the two-side merge, with no files: what a trunk's foot stands on, the trunk axis and the
row direction the merge uses, each paired trunk as the semantic BA measures it, the tree's foot chosen from both
sides' estimates, and the tree's local ground fitted to both sides' points (pipeline.merge)."""

from __future__ import annotations

import numpy as np

from orchard_mapping.core.cylinder import Cylinder
from orchard_mapping.core.geometry import SlabIndex
from orchard_mapping.core.ground import GroundParams
from orchard_mapping.core.semantic_ba import TrunkShape, trunk_frame
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.core.trunks import TrunkLandmark, ground_around_trunk


def ground_kind(lm: TrunkLandmark) -> int:
    """What a trunk's foot stands on: 2 its local ground, 1 the wider ground (no local one), 0 neither
    (its lowest visible point)."""
    return 2 if lm.ground is not None else 1 if "diameter_height_from_wide_ground" in lm.flags else 0


def merge_axis(lm: TrunkLandmark) -> np.ndarray:
    """The trunk axis the merge uses: with the taper modelled when it was fitted (TrunkLandmark.merge_axis)."""
    return lm.merge_axis if lm.merge_axis is not None else lm.axis


def row_direction(bases: np.ndarray) -> np.ndarray:
    """(3,) unit: the row's direction through trunk bases (T, 3) (their first principal axis), T >= 2."""
    return np.linalg.svd(bases - bases.mean(axis=0), full_matrices=False)[2][0]


def trunk_shapes(sm: SideMap, ids: list[int], T_map_odom: np.ndarray, height_m: float, row_map: np.ndarray
                 ) -> list[TrunkShape]:
    """Each paired trunk of a side as the semantic BA measures it: its frame (origin on the whole-trunk
    axis at the diameter height, z along it, x along the row: row_map (3,) in map) and local ground, in the camera of the
    observation that saw most of it. (The band cylinder's own axis, fitted on 16 cm of trunk, tilts
    5-18 deg off the whole trunk's on the 10-tree rows: only its radius is used.)"""
    by_id = {t.id: t for t in sm.trunks}
    out = []
    for tree, lid in enumerate(ids):
        lm = by_id[lid]
        k = max(lm.observations, key=lambda o: o.band_pixels + int(o.detection.mask.sum())).keyframe
        axis_map = T_map_odom[:3, :3] @ merge_axis(lm)
        origin_map = T_map_odom[:3, :3] @ (lm.base + height_m * merge_axis(lm)) + T_map_odom[:3, 3]
        T_map_cam = T_map_odom @ sm.keyframe_poses[k]
        ground = None
        if lm.ground is not None:
            R, t = sm.keyframe_poses[k][:3, :3], sm.keyframe_poses[k][:3, 3]
            n = np.asarray(lm.ground.normal, float)
            ground = np.array([*(R.T @ n), n @ t + lm.ground.offset])
        out.append(TrunkShape(tree, k, np.linalg.inv(T_map_cam) @ trunk_frame(origin_map, axis_map, row_map), ground,
                              grounded=ground_kind(lm) > 0))
    return out


# m: the union of both sides' points near a tree is cropped to this cube (half side) before the local
# ground's disk is cut out of it (cheaper than measuring every point of the row against every axis).
FOOT_CROP_M = 1.0


def two_side_ground(clouds: dict[str, SlabIndex], Tt: np.ndarray, foot: np.ndarray, radius: float,
                    ground: GroundParams, rng: np.random.Generator):
    """The tree's local ground fitted to both sides' points around the shared trunk (frame `map`).

    Each side sees its half of the 0.5 m disk, often only a patch of it away from the trunk, and a plane
    through a patch is an extrapolation at the trunk. Together the sides see the disk from both
    directions: the plane is pinned on both sides of the trunk (the paper's semantic BA shares one plane
    per tree for the same reason). Tt (4, 4) the shared trunk frame (z up its axis); foot (3,) the
    per-side estimate of the foot (the disk's centre); radius m the trunk's; ground: the configuration's
    ground parameters (cfg.ground). None if no plane passes."""
    near = [c.within_cube(foot, FOOT_CROP_M) for c in clouds.values()]
    pts = np.concatenate(near) if near else np.zeros((0, 3))
    z = Tt[:3, 2]
    o_bottom = Tt[:3, 3] + float((foot - Tt[:3, 3]) @ z) * z
    return ground_around_trunk(pts, o_bottom, Cylinder(z, Tt[:3, 3], radius), ground, rng)


def foot_on_shared_axis(Tt: np.ndarray, heights: list[tuple[int, float]]) -> np.ndarray:
    """(3,) map: the foot on the shared trunk Tt (4, 4; z up its axis) after the semantic BA; heights: per side,
    (ground_kind of its trunk, its base's height m along z from Tt's origin, placed by that side's adjusted
    camera). A local ground (within 0.5 m) is the best evidence of the foot, the wide ground (1 m, rougher: on
    slope_weeds a tree with a local ground on one side and a wide one on the other came out 7 cm high from their
    mean) the next; a side with neither has only its lowest trunk point (weeds may hide the foot: 15 cm too high
    on the 2-tree test row). The best kind present decides; with neither, the lower base."""
    z = Tt[:3, 2]
    best = max(kind for kind, _ in heights)
    chosen = [hh for kind, hh in heights if kind == best]
    return Tt[:3, 3] + (float(np.mean(chosen)) if best else min(chosen)) * z


def foot_from_feet(feet: list[tuple[int, np.ndarray]]) -> np.ndarray:
    """(3,) map: the tree's foot without the semantic BA: the mean of the feet on the best ground either side has
    (as in foot_on_shared_axis); feet: per side, (ground_kind of its trunk, its base (3,) carried into map)."""
    best = max(kind for kind, _ in feet)
    return np.mean([p for kind, p in feet if kind == best], axis=0)


# A one-sided trunk this close (m, across the ground) to a tree both sides saw is that tree, seen again by a
# side whose trunk the pairing missed: orchards plant trees 0.5 m apart at the closest, a trunk is < 0.3 m wide.
DUPLICATE_TREE_M = 0.25
# A one-sided trunk this far (m) across the row from the line through the trees both sides saw is not in this
# row: a post or trunk of the next row seen through a gap, a detection on a weed. Rows are 3-4 m apart; a
# row's trunks stand within ~0.2 m of its line.
OFF_ROW_M = 0.5


# m beyond the two radii within which a one-sided trunk and the other side's post are one object (the post's
# place is half way up what its views saw: a degree of lean is ~2 cm there)
POST_OF_OTHER_SIDE_TOL_M = 0.05


def other_sides_post(position: np.ndarray, radius_m: float, trunk_frames: int, own_post_frames: int,
                     posts: list[tuple[np.ndarray, float, int]], up: np.ndarray) -> int | None:
    """Whether a trunk seen from one side only (its foot position (3,), radius m, the frames that called it a
    trunk and those of its own side that called it a post) is a post the other side modelled (posts: (place
    (3,), radius m, frames) in the same frame): the post's frames when it stands there (across the ground within
    the two radii and POST_OF_OTHER_SIDE_TOL_M) and the frames calling the object a post are at least those
    calling it a trunk (a tie going to the post, as within a side: core.posts.separate_trunks_from_posts); else
    None."""
    unit_up = np.asarray(up, float) / np.linalg.norm(up)
    for place, radius, frames in posts:
        rel = np.asarray(place, float) - np.asarray(position, float)
        if np.linalg.norm(rel - (rel @ unit_up) * unit_up) <= radius + radius_m + POST_OF_OTHER_SIDE_TOL_M:
            return frames if frames + own_post_frames >= trunk_frames else None
    return None


def _across_ground(positions: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(T, 3) the positions (T, 3) with their height along the unit up (3,) taken out: distances across the
    ground, where trees are told apart (a foot misplaced up or down is still the same trunk)."""
    P = np.asarray(positions, float).reshape(-1, 3)
    return P - np.outer(P @ up, up)


def opposite_one_sided_pairs(front_only: np.ndarray, back_only: np.ndarray, up: np.ndarray) -> list[tuple[int, int]]:
    """(i, j) pairs of a front-only tree (front_only (F, 3) positions) and a back-only one (back_only (B, 3))
    within DUPLICATE_TREE_M of each other across the ground (unit up (3,)), each the other's nearest: one trunk
    both sides saw, whose pairing the merge missed."""
    if not len(front_only) or not len(back_only):
        return []
    up = np.asarray(up, float) / np.linalg.norm(up)
    f, b = _across_ground(front_only, up), _across_ground(back_only, up)
    d = np.linalg.norm(f[:, None, :] - b[None, :, :], axis=2)  # (F, B)
    near_f, near_b = np.argmin(d, axis=1), np.argmin(d, axis=0)
    return [(i, int(near_f[i])) for i in range(len(f))
            if d[i, near_f[i]] < DUPLICATE_TREE_M and near_b[near_f[i]] == i]


def one_sided_outliers(positions: np.ndarray, two_sided: np.ndarray, up: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """For trees at positions (T, 3) (two_sided (T,) bool: seen from both sides) in a frame with unit up (3,):
    (duplicate_of (T,) int: the two-sided tree a one-sided one repeats, -1 none; off_row (T,) bool: a one-sided
    tree further than OFF_ROW_M across the row line, which needs two two-sided trees)."""
    both = np.asarray(two_sided, bool)
    up = np.asarray(up, float) / np.linalg.norm(up)
    flat = _across_ground(positions, up)
    dup = np.full(len(flat), -1)
    off = np.zeros(len(flat), bool)
    idx = np.flatnonzero(both)
    if not len(idx):
        return dup, off
    one = np.flatnonzero(~both)
    d = np.linalg.norm(flat[one, None, :] - flat[None, idx, :], axis=2)  # (O, B)
    near = d.min(axis=1) < DUPLICATE_TREE_M
    dup[one[near]] = idx[np.argmin(d[near], axis=1)]
    if len(idx) >= 2:
        along = row_direction(flat[idx])
        across = np.cross(up, along)
        c = flat[idx].mean(axis=0)
        off[one] = np.abs((flat[one] - c) @ across) > OFF_ROW_M
        off[dup >= 0] = False
    return dup, off
