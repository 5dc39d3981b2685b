"""Benchmark: does TSDF fusion lean a trunk? Trunk axes from the simulator's TRUE camera poses, before and
after fusion.

For each side of a simulated row, every `--every`-th frame is rendered (noise-free and with the sensor's
noise) and fused with its true pose into TSDF volumes (core.fusion.TsdfFusion) of several truncations.
Each tree's trunk axis is then read as the line through circles fitted to 8 cm slices of its points
(model-free: no taper, no cylinder) from: the raw depth pixels of the trunk (noisy, points more than 3 cm
off the true surface left out, i.e. flying pixels), and each volume's surface. Printed: the lean against
the true axis in the vertical plane through the camera's viewing direction (deg, + away from the camera),
per tree and the median. No pose error enters: what leans here leans because of the fusion.

Usage:
  python benchmarks/tsdf_trunk_lean.py [--trees 3] [--seed 0] [--every 2] [--trunc 0.02 0.04 0.08]
"""

from __future__ import annotations

import argparse

import numpy as np
from rich.console import Console
from rich.table import Table

from orchard_mapping.core.tsdf import TsdfFusion
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.scene import Cls
from orchard_mapping.sim.simulate import Rig
from orchard_mapping.sim.truth import trunk_axis_at_height
from trunk_tilt import slice_centre_line  # the script's own folder is on sys.path

VOXEL_M = 0.01  # m, the default fusion.voxel_size_m


def _true_axis(tree) -> tuple[np.ndarray, np.ndarray]:
    base, top = trunk_axis_at_height(tree, 0.0), trunk_axis_at_height(tree, tree.clear_height)
    return base, (top - base) / np.linalg.norm(top - base)


def _slice_axis(P: np.ndarray, tree) -> np.ndarray | None:
    """(3,) unit axis through slice circles of the trunk points P (N, 3) near the true trunk surface."""
    base, a = _true_axis(tree)
    rel = P - base
    h = rel @ a
    radial = np.linalg.norm(rel - h[:, None] * a, axis=1)
    on = (h > 0.05) & (h < tree.clear_height) & (np.abs(radial - np.interp(h, tree.axis_s, tree.axis_diam) / 2) < 0.03)
    rel, h = rel[on], h[on]
    e1 = np.cross(a, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    return slice_centre_line(rel, h, a, e1, e2, 0.1, tree.clear_height - 0.1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trees", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--every", type=int, default=2)
    ap.add_argument("--trunc", type=float, nargs="+", default=[0.02, 0.04, 0.08], help="TSDF truncations, m")
    args = ap.parse_args()
    sc = load_scenario("standard", {"row.n_trees": args.trees, "camera.rate_hz": 10})
    rig = Rig.build(sc, args.seed)
    K = rig.intrinsics
    u, v = np.meshgrid(np.arange(K.width), np.arange(K.height))
    rays = np.stack([(u - K.cx) / K.fx, (v - K.cy) / K.fy, np.ones(u.shape)], -1)  # (H, W, 3), z = 1
    noise = np.random.default_rng([args.seed, 5])
    console = Console(width=140)
    for k, side in enumerate(("front", "back")):
        path = rig.path(side, np.random.default_rng([args.seed, 1, k]))
        volumes = {f"noise-free, trunc {t * 100:g} cm": (TsdfFusion(K, VOXEL_M, t, 3.0), False) for t in args.trunc}
        volumes["noisy, trunc 4 cm"] = (TsdfFusion(K, VOXEL_M, 0.04, 3.0), True)
        raw: dict[int, list[np.ndarray]] = {t.id: [] for t in rig.scene.trees}
        views = []
        for i in range(0, len(path.stamps), args.every):
            T = path.poses[i]
            out = rig.renderer.render(T, 0.0)
            colour, depth = rig.sensor.apply(out, noise)
            for vol, noisy in volumes.values():
                vol.integrate(depth if noisy else out.depth.astype(np.float32), colour if noisy else out.color, T)
            views.append(T[:3, 2])
            m = (out.cls == Cls.TRUNK) & (depth > 0) & (depth < 3.0)
            P = (rays[m] * depth[m][:, None]) @ T[:3, :3].T + T[:3, 3]
            for t in rig.scene.trees:
                raw[t.id].append(P[out.inst[m] == t.id])
        view = np.mean(views, axis=0)
        view[2] = 0.0
        view /= np.linalg.norm(view)  # the camera's horizontal viewing direction
        clouds = {"depth pixels (noisy)": None} | {name: vol.extract_point_cloud()[0].astype(float)
                                                   for name, (vol, _) in volumes.items()}
        tab = Table(title=f"{side}: trunk lean against the truth from true poses, deg (+ away from the camera)")
        tab.add_column("points")
        for t in rig.scene.trees:
            tab.add_column(f"tree {t.id}", justify="right")
        tab.add_column("median", justify="right")
        for name, cloud in clouds.items():
            leans = []
            for t in rig.scene.trees:
                ax = _slice_axis(np.vstack(raw[t.id]) if cloud is None else cloud, t)
                a = _true_axis(t)[1]
                leans.append(np.nan if ax is None else float(np.degrees(np.arcsin(ax @ view) - np.arcsin(a @ view))))
            tab.add_row(name, *(f"{x:.2f}" for x in leans), f"{np.nanmedian(leans):.2f}")
        console.print(tab)


if __name__ == "__main__":
    main()
