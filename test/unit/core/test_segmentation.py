"""core.segmentation: cutting planes vs shrink-and-expand on synthetic rows with per-point truth."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.core.segmentation import (
    cutting_plane_segmentation,
    ground_and_post_masks,
    shrink_and_expand_segmentation,
)
from orchard_mapping.sim.point_rows import KIND_GROUND, KIND_POST, KIND_TREE, synthetic_row

ROW = np.array([1.0, 0.0, 0.0])


@pytest.mark.parametrize("seed", [0, 2, 3])
def test_branch_over_the_neighbour_goes_to_its_own_tree(seed):
    """Two crowns at 0.7 m overlapping, the first with a branch and leaf clump over the second's crown:
    the cutting plane gives the branch to the neighbour; shrink-and-expand keeps it (seeds 0, 2-5: 99.0-99.6 %
    vs 96.2-97.4 % for the cutting plane; seed 1 never separates: see the next test)."""
    r = synthetic_row(seed, n_trees=2, spacing_m=0.7, branch_over=(0,))
    m = r.kind == KIND_TREE
    p, t = r.points[m], r.tree[m]
    cp = np.mean(cutting_plane_segmentation(p, r.trunk_positions, ROW) == t)
    se = shrink_and_expand_segmentation(p, r.trunk_positions, ROW)
    acc = np.mean(se.tree == t)
    assert se.pair_separated.all()
    assert acc >= 0.97
    assert acc > cp + 0.01


def test_a_pair_that_never_separates_is_flagged_and_cut_by_the_plane():
    """Seed 1: the shrink never leaves a principal region at each trunk; the pair is flagged and its points
    take the cutting plane's labels."""
    r = synthetic_row(1, n_trees=2, spacing_m=0.7, branch_over=(0,))
    p = r.points[r.kind == KIND_TREE]
    se = shrink_and_expand_segmentation(p, r.trunk_positions, ROW)
    assert not se.pair_separated[0] and np.isnan(se.pair_split_depth_m[0])
    # the pair's own plane (perpendicular to the trunk-to-trunk line) vs the row track's: nearly the same
    assert np.mean(se.tree == cutting_plane_segmentation(p, r.trunk_positions, ROW)) > 0.99


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_separate_crowns_both_methods_near_perfect(seed):
    r = synthetic_row(seed, n_trees=3, spacing_m=1.4, radius_along_m=(0.4, 0.5))
    m = r.kind == KIND_TREE
    p, t = r.points[m], r.tree[m]
    assert np.mean(cutting_plane_segmentation(p, r.trunk_positions, ROW) == t) >= 0.99
    assert np.mean(shrink_and_expand_segmentation(p, r.trunk_positions, ROW).tree == t) >= 0.99


def test_ground_and_posts_are_masked_on_a_slope():
    r = synthetic_row(0, n_trees=3, spacing_m=0.9, posts_between=(0,), slope_deg=(4.0, 2.0))
    cut = cutting_plane_segmentation(r.points, r.trunk_positions, ROW)
    ground, post = ground_and_post_masks(r.points, cut, r.ground_points, r.ground_normals, ground_margin_m=0.05,
                                         post_points=r.post_points, post_radius_m=r.post_radius_m, post_margin_m=0.03)
    assert np.mean(ground[r.kind == KIND_GROUND]) > 0.97  # the plane is the trunks' local one, ground undulates 0
    assert np.all(post[r.kind == KIND_POST])
    assert np.mean(ground[r.kind == KIND_TREE] | post[r.kind == KIND_TREE]) < 0.02


def _wire(rng, x0, x1, height, across, spacing=0.01, noise=0.002):
    x = np.arange(x0, x1, spacing)
    return np.column_stack([x, np.full_like(x, across), np.full_like(x, height)]) + rng.normal(0, noise, (len(x), 3))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_trellis_wire_is_found_where_it_shows_and_followed_where_leaves_hide_it(seed):
    """A wire at 1.5 m seen unbroken between crowns and only in stubs of 10 cm inside them is a wire over its
    whole length; the crowns' leaves and the flat ground are not, nor three clumps of leaves 3 cm from the hidden
    wire (the 6 cm block round it took 73-100 % of them, seeds 0-5; the tube round its line 0-1.7 %)."""
    from orchard_mapping.core.segmentation import row_line_mask

    rng = np.random.default_rng(seed)
    r = synthetic_row(seed, n_trees=3, spacing_m=1.4, radius_along_m=(0.4, 0.5))
    open_span = _wire(rng, 0.5, 0.95, 1.5, 0.0)  # between crowns 0 and 1 (trunks at 0, 1.4)
    stubs = np.concatenate([_wire(rng, x, x + 0.1, 1.5, 0.0) for x in (1.1, 1.35, 1.6)])  # inside crown 1
    ang = rng.uniform(0, 2 * np.pi, 3)
    clumps = np.concatenate([np.array([x, 0.03 * np.cos(a), 1.5 + 0.03 * np.sin(a)]) + rng.normal(0, 0.004, (40, 3))
                             for x, a in zip((1.22, 1.47, 1.72), ang, strict=True)])
    pts = np.concatenate([r.points, open_span, stubs, clumps])
    h = np.concatenate([np.sum((r.points - r.ground_points[0]) * r.ground_normals[0], axis=1),
                        np.full(len(open_span) + len(stubs) + len(clumps), 1.5)])
    wire = row_line_mask(pts, h, min_height_m=0.3)
    n, m = len(r.points), len(r.points) + len(open_span)
    assert wire[n:m].mean() > 0.95
    assert wire[m:m + len(stubs)].mean() > 0.9  # the stubs: within reach of the open span
    assert wire[m + len(stubs):].mean() < 0.05  # leaves beside the hidden wire
    assert row_line_mask(pts, h, min_height_m=0.3, tube_factor=0.0)[m + len(stubs):].mean() > 0.5  # the block's
    assert wire[:n][r.kind == KIND_TREE].mean() < 0.01  # leaves are not lines along the row
    assert not wire[:n][r.kind == KIND_GROUND].any()  # below min_height_m
