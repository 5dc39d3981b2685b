"""Benchmark: how each side's trunk axes lean against the truth, towards or away from that side's camera.

The two-side merge makes both sides' halves of a trunk one axis; a lean of each side's axes towards its
own camera then tilts the sides against each other about the row (docs/history.md, "Why the merged map
leaned about the row"). For each side of a reconstructed row (benchmarks/merge.py's sides.pkl) the side's map
is placed on its true trajectory by one rigid fit (eval.metrics.fit_map_to_world), and each trunk's axis is
compared with the true one in the vertical plane through the camera's viewing direction: the plain
cylinder axis (TrunkLandmark.axis), the cone axis the merge uses (merge_axis), and a model-free axis
through circles fitted to 8 cm slices of the fused trunk points; and each local ground's normal.
Positive: leaning away from the camera. Prints the per-tree values and the medians.

Usage:
  python benchmarks/trunk_tilt.py CASE_DIR [--sides sides_masks.pkl]   (a benchmarks/merge.py case folder:
      sim/ and sides.pkl)
"""

from __future__ import annotations

import argparse
import pickle
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table
from scipy.optimize import least_squares

from orchard_mapping.core.cylinder import perpendicular_basis
from orchard_mapping.core.geometry import matrix_to_quat
from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.eval.evaluate import trunk_scene_points
from orchard_mapping.eval.ground_truth import load_ground_truth
from orchard_mapping.eval.metrics import fit_map_to_world

SLICE_M = 0.08  # m of trunk per circle fit
MIN_SLICE_POINTS = 40


def _circle(xy: np.ndarray) -> np.ndarray:
    """(cx, cy, r) of the circle through points xy (N, 2): algebraic fit, then Huber LM."""
    A = np.c_[2 * xy, np.ones(len(xy))]
    c = np.linalg.lstsq(A, (xy ** 2).sum(1), rcond=None)[0]
    r0 = np.sqrt(max(c[2] + c[:2] @ c[:2], 1e-6))
    sol = least_squares(lambda p: np.linalg.norm(xy - p[:2], axis=1) - p[2], np.r_[c[:2], r0], loss="huber",
                        f_scale=0.003)
    return sol.x


def _slice_axis(lm, cloud: np.ndarray) -> np.ndarray | None:
    """(3,) unit axis through the centres of circles fitted to slices of the trunk's fused points."""
    a = lm.axis / np.linalg.norm(lm.axis)
    e1, e2 = perpendicular_basis(a)
    rel = cloud - lm.base
    h = rel @ a
    r0 = lm.diameter_m / 2 if lm.diameter_m else 0.05
    near = (h > 0.1) & (h < lm.length_m - 0.05) & (np.abs(np.linalg.norm(rel - h[:, None] * a, axis=1) - r0) < 0.02)
    return slice_centre_line(rel[near], h[near], a, e1, e2, 0.1, lm.length_m - 0.05)


def slice_centre_line(Q: np.ndarray, hq: np.ndarray, a: np.ndarray, e1: np.ndarray, e2: np.ndarray, h_lo: float,
                      h_hi: float) -> np.ndarray | None:
    """(3,) unit line through the centres of circles fitted to SLICE_M slices (h_lo..h_hi along a) of trunk
    points Q (N, 3) relative to a point on the axis, hq (N,) their heights along a; e1, e2 across a."""
    centres = []
    for h0 in np.arange(h_lo, h_hi, SLICE_M):
        m = (hq >= h0) & (hq < h0 + SLICE_M)
        if m.sum() >= MIN_SLICE_POINTS:
            cx, cy, _ = _circle(np.c_[Q[m] @ e1, Q[m] @ e2])
            centres.append(cx * e1 + cy * e2 + (h0 + SLICE_M / 2) * a)
    if len(centres) < 3:
        return None
    C = np.array(centres)
    ax = np.linalg.svd(C - C.mean(0))[2][0]
    return ax if ax @ a > 0 else -ax


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", type=Path)
    ap.add_argument("--sides", default="sides.pkl", help="the sides file in the case folder (sides_masks.pkl: "
                                                         "trunks from the simulator's masks, merge.py --masks)")
    args = ap.parse_args()
    with (args.case / args.sides).open("rb") as f:
        sides = pickle.load(f)
    gt = load_ground_truth(args.case / "sim" / "ground_truth.json")
    bases = np.array([t.trunk_base for t in gt.trees])
    console = Console(width=160)
    for side, sm in sides.items():
        tr = StampedTrajectory(sm.keyframe_stamps, sm.keyframe_poses[:, :3, 3], matrix_to_quat(sm.keyframe_poses[:, :3, :3]))
        A = fit_map_to_world(tr, gt.sides[side].trajectory, gt.sides[side].T_world_odom, 0.005,
                             trunk_scene_points(gt))
        view = gt.sides[side].T_world_odom[:3, :3] @ sm.keyframe_poses[:, :3, 2].mean(0)
        view[2] = 0.0
        view /= np.linalg.norm(view)  # the camera's horizontal viewing direction, world

        def lean(v: np.ndarray | None, truth: np.ndarray) -> float:
            if v is None:
                return float("nan")
            w = A[:3, :3] @ v  # noqa: B023 - lean() is called within this iteration only
            w = w / np.linalg.norm(w)
            w = w if w[2] > 0 else -w
            return float(np.degrees(np.arcsin(w @ view) - np.arcsin(truth @ view)))  # noqa: B023 - as above

        rows = []
        cloud = sm.cloud_points.astype(float)
        for lm in sm.trunks:
            k = int(np.argmin(np.linalg.norm(bases - (A[:3, :3] @ lm.base + A[:3, 3]), axis=1)))
            t = gt.trees[k]
            rows.append((lm.id, k, lean(lm.axis, t.trunk_axis), lean(lm.merge_axis, t.trunk_axis),
                         lean(_slice_axis(lm, cloud), t.trunk_axis),
                         lean(lm.ground.normal if lm.ground is not None else None, t.ground_normal)))
        tab = Table(title=f"{side}: lean against the truth, deg (+ away from the camera)")
        for col in ("trunk", "tree", "plain cylinder", "cone (merge)", "slice circles", "local ground normal"):
            tab.add_column(col, justify="right")
        for r in rows:
            tab.add_row(str(r[0]), str(r[1]), *(f"{v:.2f}" for v in r[2:]))
        med = np.nanmedian(np.array([r[2:] for r in rows], float), axis=0)
        tab.add_row("median", "", *(f"{v:.2f}" for v in med))
        console.print(tab)


if __name__ == "__main__":
    main()
