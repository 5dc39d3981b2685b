"""core.trees: the per-tree geometry of the two-side merge (what a foot stands on, the merge's trunk axis and
row direction, the foot chosen from both sides' estimates, the local ground fitted to both sides' points)."""

from types import SimpleNamespace

import numpy as np

from orchard_mapping.core.geometry import SlabIndex
from orchard_mapping.core.ground import GroundParams
from orchard_mapping.core.trees import (
    foot_from_feet,
    foot_on_shared_axis,
    ground_kind,
    merge_axis,
    row_direction,
    two_side_ground,
)


def _trunk(ground=None, flags=(), axis=(0.0, 0.0, 1.0), merge=None):
    return SimpleNamespace(ground=ground, flags=list(flags), axis=np.array(axis), merge_axis=merge)


def test_ground_kind_ranks_local_over_wide_over_none():
    assert ground_kind(_trunk(ground=object())) == 2
    assert ground_kind(_trunk(flags=["diameter_height_from_wide_ground"])) == 1
    assert ground_kind(_trunk()) == 0


def test_merge_axis_prefers_the_tapered_fit():
    tapered = np.array([0.0, 0.1, 1.0])
    assert np.array_equal(merge_axis(_trunk(merge=tapered)), tapered)
    assert np.array_equal(merge_axis(_trunk()), [0.0, 0.0, 1.0])


def test_row_direction_is_the_bases_principal_axis():
    bases = np.array([[0.0, 0.0, 0.0], [2.0, 0.01, 0.0], [4.0, -0.01, 0.0], [6.0, 0.0, 0.0]])
    d = row_direction(bases)
    assert abs(np.linalg.norm(d) - 1.0) < 1e-12
    assert abs(abs(d[0]) - 1.0) < 1e-4


def test_foot_on_shared_axis_takes_the_best_ground_kind():
    Tt = np.eye(4)
    Tt[:3, 3] = [1.0, 2.0, 0.5]
    # a local ground on one side beats the other's lowest trunk point
    assert np.allclose(foot_on_shared_axis(Tt, [(2, -0.5), (0, -0.3)]), [1.0, 2.0, 0.0])
    # the same kind on both sides: their mean
    assert np.allclose(foot_on_shared_axis(Tt, [(1, -0.4), (1, -0.6)]), [1.0, 2.0, 0.0])
    # neither side with a ground: the lower base
    assert np.allclose(foot_on_shared_axis(Tt, [(0, -0.2), (0, -0.45)]), [1.0, 2.0, 0.05])


def test_foot_from_feet_averages_the_best_kind_only():
    a, b = np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.2])
    assert np.allclose(foot_from_feet([(2, a), (1, b)]), a)
    assert np.allclose(foot_from_feet([(1, a), (1, b)]), [0.0, 0.0, 0.1])


def test_two_side_ground_fits_the_plane_both_sides_see():
    g = np.arange(-0.7, 0.7, 0.01)
    x, y = np.meshgrid(g, g)
    pts = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) > 0.08]  # the trunk's own footprint unseen
    # each side sees its half of the disk
    clouds = {"front": SlabIndex(pts[pts[:, 1] < 0]), "back": SlabIndex(pts[pts[:, 1] >= 0])}
    Tt = np.eye(4)
    Tt[:3, 3] = [0.0, 0.0, 0.3]  # the shared trunk's frame at the diameter height, z up its axis
    fit = two_side_ground(clouds, Tt, np.array([0.0, 0.0, 0.02]), 0.05, GroundParams(), np.random.default_rng(0))
    assert fit is not None
    assert abs(fit.point[2]) < 0.005
    assert abs(abs(np.asarray(fit.normal)[2]) - 1.0) < 1e-3
    assert two_side_ground({}, Tt, np.zeros(3), 0.05, GroundParams(), np.random.default_rng(0)) is None


def test_one_sided_trunks_that_repeat_a_tree_or_stand_off_the_row_are_found():
    """Five two-sided trees along x (1 m apart, up z); one-sided: one 6 cm from tree 2 (the same tree seen
    again), one 0.9 m across the row (not this row's), one on the row between trees 3 and 4 (a tree one side
    alone saw: kept)."""
    from orchard_mapping.core.trees import one_sided_outliers

    two = np.column_stack([np.arange(5.0), 0.05 * np.sin(np.arange(5.0)), np.full(5, -1.2)])
    one = np.array([[2.05, 0.03, -1.1], [1.5, 0.9, -1.3], [3.5, 0.02, -1.2]])
    P = np.vstack([two, one])
    dup, off = one_sided_outliers(P, np.r_[np.ones(5, bool), np.zeros(3, bool)], np.array([0.0, 0.0, 1.0]))
    assert dup.tolist() == [-1] * 5 + [2, -1, -1]
    assert off.tolist() == [False] * 6 + [True, False]
    # the distance is across the ground: the repeat 10 cm below its tree is still a repeat
    low = P.copy()
    low[5, 2] -= 0.1
    assert one_sided_outliers(low, np.r_[np.ones(5, bool), np.zeros(3, bool)], np.array([0.0, 0.0, 1.0]))[0][5] == 2
    # without two-sided trees nothing is judged
    d0, o0 = one_sided_outliers(one, np.zeros(3, bool), np.array([0.0, 0.0, 1.0]))
    assert (d0 == -1).all() and not o0.any()


def test_a_front_only_and_a_back_only_trunk_at_one_place_are_one_tree():
    """pipeline.merge.join_opposite_one_sided: the pairing missed a trunk both sides saw (front-only and
    back-only trees 1 cm apart): one tree with both sides' trunks, the lower foot, the mean diameter, flagged;
    a one-sided tree elsewhere and two one-sided trees of the same side stay as they are."""
    from orchard_mapping.io.results import ResultTree
    from orchard_mapping.pipeline.merge import PAIRED_AFTER_MERGE, join_opposite_one_sided

    trees = [
        ResultTree(0, (0.0, 0.0, 0.0), 0.05, per_side={"front": {"trunk_id": 0}, "back": {"trunk_id": 0}}),
        ResultTree(1, (1.0, 0.0, 0.1), 0.04, per_side={"front": {"trunk_id": 1}}, flags=("seen_from_front_only",)),
        ResultTree(2, (1.01, 0.0, -0.14), 0.06, per_side={"back": {"trunk_id": 1}}, flags=("seen_from_back_only",)),
        ResultTree(3, (2.0, 0.0, 0.0), 0.05, per_side={"front": {"trunk_id": 2}}, flags=("seen_from_front_only",)),
        ResultTree(4, (2.05, 0.0, 0.0), 0.05, per_side={"front": {"trunk_id": 3}}, flags=("seen_from_front_only",)),
    ]
    out = join_opposite_one_sided(trees, np.array([0.0, 0.0, 1.0]))
    assert [t.id for t in out] == [0, 1, 3, 4]
    j = out[1]
    assert set(j.per_side) == {"front", "back"} and j.position == (1.01, 0.0, -0.14)
    assert abs(j.trunk_diameter_m - 0.05) < 1e-12 and j.flags == (PAIRED_AFTER_MERGE,)
    assert out[2].flags == ("seen_from_front_only",)


def test_a_one_sided_trunk_the_other_side_saw_as_a_post_is_that_post_by_the_frames_of_both_sides():
    """A row-end post a trunk in 18 front frames and a post in 12 more, a post in 13 back frames: 25 against
    18, a post. The same trunk without its own side's post frames, or with the post elsewhere, stays a trunk;
    a tie goes to the post."""
    from orchard_mapping.core.trees import other_sides_post

    up = np.array([0.0, 0.0, 1.0])
    foot = np.array([0.88, 0.55, 1.26])
    post = (np.array([0.86, 0.53, 2.2]), 0.045, 13)  # its place half way up what its views saw
    assert other_sides_post(foot, 0.05, 18, 12, [post], up) == 13
    assert other_sides_post(foot, 0.05, 18, 0, [post], up) is None  # 13 < 18
    assert other_sides_post(foot, 0.05, 18, 5, [post], up) == 13  # 18 = 18: a post
    far = (post[0] + [0.25, 0.0, 0.0], 0.045, 40)  # 25 cm along the row: the next tree's post, not this
    assert other_sides_post(foot, 0.05, 18, 12, [far], up) is None
    assert other_sides_post(foot, 0.05, 18, 12, [], up) is None
