"""Per-point segmentation score (eval.segmentation) and the simulator's surface samples it scores against."""

from __future__ import annotations

import numpy as np
import pytest

from orchard_mapping.errors import ResultFormatError
from orchard_mapping.eval.segmentation import load_tree_surfaces, segmentation_score


def _two_crowns(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Two crowns 0.95 m apart, 5 cm between them (spheres of 0.45 m, ~2 cm samples), a ground patch (-1)."""
    n = 20000
    d = rng.normal(size=(2 * n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    crowns = 0.45 * d + np.repeat([[0.0, 0, 1.5], [0.95, 0, 1.5]], n, axis=0)
    ground = np.column_stack([rng.uniform(-1, 2, 5000), rng.uniform(-1, 1, 5000), np.zeros(5000)])
    return np.concatenate([crowns, ground]), np.repeat([0, 1, -1], [n, n, 5000])


def test_score_counts_points_given_to_the_matched_tree_and_the_touching_zone():
    rng = np.random.default_rng(3)
    surf, tree = _two_crowns(rng)
    T = np.eye(4)
    T[:3, 3] = [10.0, -2.0, 0.5]  # map = world + offset: the score must apply T_map_world
    pts = surf[::2] + rng.normal(scale=0.005, size=(len(surf[::2]), 3)) + T[:3, 3]
    truth = tree[::2]
    # the product's labels: result ids 7 (true 0) and 9 (true 1); every point with x > 0.35 (world) given to 9
    lab = np.where(truth == 0, 7, np.where(truth == 1, 9, -1))
    lab[(pts[:, 0] - 10.0 > 0.35) & (truth == 0)] = 9
    lab[truth == -1] = 7  # ground given to a tree: off-tree, not in the accuracy
    s = segmentation_score(pts, lab, surf, tree, T, {0: 7, 1: 9})
    on = truth >= 0
    expect = np.mean(lab[on] == np.where(truth[on] == 0, 7, 9))
    assert s.n_points == int(on.sum())
    assert s.accuracy == pytest.approx(expect, abs=1e-9)
    assert 0.9 < s.accuracy < 1.0
    # the errors lie where the crowns touch: the accuracy there is lower than overall
    assert s.accuracy_near_neighbour is not None and s.accuracy_near_neighbour < s.accuracy
    assert s.off_tree == pytest.approx(np.mean(truth[lab >= 0] == -1), abs=1e-9)
    assert s.unassigned == 0.0


def test_points_far_from_every_surface_and_unmatched_trees_are_left_out():
    rng = np.random.default_rng(4)
    surf, tree = _two_crowns(rng)
    far = np.array([[0.4, 3.0, 1.5], [5.0, 0.0, 0.2]])  # 3 m off the crowns: no surface within tolerance
    pts = np.concatenate([surf[tree == 0][:100], far])
    lab = np.full(len(pts), -1)
    s = segmentation_score(pts, lab, surf, tree, np.eye(4), {0: 4})
    assert s.n_points == 100 and s.accuracy == 0.0 and s.unassigned == 1.0
    s1 = segmentation_score(pts, lab, surf, tree, np.eye(4), {1: 4})  # tree 0 unmatched: nothing to score
    assert s1.n_points == 0


def test_a_file_that_is_not_surfaces_is_refused_with_its_path(tmp_path):
    bad = tmp_path / "tree_surfaces.npz"
    np.savez(bad, points=np.zeros((5, 3)), tree=np.zeros(4))
    with pytest.raises(ResultFormatError, match="tree_surfaces.npz"):
        load_tree_surfaces(bad)
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(ResultFormatError, match="junk.npz"):
        load_tree_surfaces(tmp_path / "junk.npz")
