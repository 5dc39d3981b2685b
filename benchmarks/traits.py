"""Traits stage on synthetic merged rows (orchard_mapping.sim.point_rows): time per tree and accuracy.

    .venv/bin/python benchmarks/traits.py [--trees 10] [--seeds 0 1 2] [--density 40000]

Per seed: a row of touching crowns at 0.7 m with a branch of every third tree over its neighbour, posts,
flying points and a 3 deg slope. Prints per-point segmentation accuracy (tree points) of cutting planes and
shrink-and-expand, height error, canopy volume at the voxel size against the full cloud's, and times.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from orchard_mapping.core.canopy import canopy_volume
from orchard_mapping.core.traits import TraitsParams, measure_row
from orchard_mapping.sim.point_rows import KIND_TREE, synthetic_row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trees", type=int, default=10)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--density", type=float, default=40000.0, help="canopy surface points per m^2")
    ap.add_argument("--spacing", type=float, default=0.7)
    a = ap.parse_args()
    print("| seed | points | method | acc % | s / tree | height MAE cm | vol vs full-cloud % |")
    print("|---|---|---|---|---|---|---|")
    for seed in a.seeds:
        r = synthetic_row(seed, a.trees, a.spacing, points_per_m2=a.density, branch_over=tuple(range(0, a.trees, 3)),
                          posts_between=tuple(range(1, a.trees - 1, 4)), n_flying=3 * a.trees, slope_deg=(3.0, 1.0))
        tree_pts = r.kind == KIND_TREE
        full_vol = np.array([canopy_volume(r.points[tree_pts & (r.tree == t)], r.ground_points[t], r.ground_normals[t],
                                           clear_trunk_height_m=float(r.clear_heights[t]), alpha_m=0.8)
                             for t in range(a.trees)])
        for method in ("cutting_planes", "shrink_and_expand"):
            params = TraitsParams(segmentation=method)
            t0 = time.perf_counter()
            out = measure_row(r.points, r.trunk_positions, r.ground_points, r.ground_normals, r.clear_heights,
                              np.array([1.0, 0.0, 0.0]), params, post_points=r.post_points,
                              post_radius_m=r.post_radius_m)
            dt = time.perf_counter() - t0
            acc = float(np.mean(out.tree[tree_pts] == r.tree[tree_pts]))
            h = np.array([m.height_m for m in out.trees])
            v = np.array([m.canopy_volume_m3 for m in out.trees])
            print(f"| {seed} | {len(r.points)} | {method} | {100 * acc:.2f} | {dt / a.trees:.3f} | "
                  f"{100 * np.mean(np.abs(h - r.heights)):.2f} | {100 * np.mean(np.abs(v / full_vol - 1)):.2f} |")


if __name__ == "__main__":
    main()
