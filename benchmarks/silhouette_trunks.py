"""Benchmark: trunk cylinders from silhouettes alone (core.silhouette), the colour-only merge's trunks.

For each scenario: the sides reconstructed with their trunks as benchmarks/merge.py makes them (shared
cache: sides.pkl beside the simulation; --reuse), then, for every trunk with a band, a cylinder from the
outlines of its detections' masks between the band's image rows (the band: +-`--half` m along the trunk
around the diameter height), with the side's keyframe poses and no depth. One table: per side, the
silhouette diameter's MAE and bias against the truth, the RGB-D band's (eq. objectCylinder, depth + 2D
terms) beside it, and how far the silhouette axis lies off the true axis (median, max) at the band, placed
by the true pose of the keyframe that saw the band best (the side's own drift left out).

The poses are the RGB-D sides' (metric): this isolates what silhouettes give from what a colour-only
front end's poses would add (scale and drift).

Usage:
  python benchmarks/silhouette_trunks.py [--scenarios standard slope_weeds] [--trees 10] [--rate 15]
        [--seed 0] [--workdir /tmp/merge_bench] [--reuse] [--masks] [--half 0.08] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from merge import add_case_arguments, case_sides  # noqa: E402
from orchard_mapping.core.cylinder import CylinderError  # noqa: E402
from orchard_mapping.core.geometry import pose_matrices, transform_points  # noqa: E402
from orchard_mapping.core.silhouette import TangentPlane, cylinder_from_silhouettes, outline_planes  # noqa: E402
from orchard_mapping.eval.metrics import associate_stamps  # noqa: E402
from orchard_mapping.io.results import portable_json


def _side_rows(sm: Any, gt: Any, side: str, half: float) -> dict[str, Any]:
    intr = sm.intrinsics
    g = gt.sides[side]
    i, j = associate_stamps(np.asarray(sm.keyframe_stamps), np.asarray(g.trajectory.stamps), 0.005)
    true_pose = dict(zip(i.tolist(), g.T_world_odom @ pose_matrices(np.asarray(g.trajectory.positions)[j],
                                                                   np.asarray(g.trajectory.quaternions)[j]), strict=True))
    base = np.array([t.trunk_base for t in gt.trees]).reshape(-1, 3)
    top = np.array([t.trunk_top for t in gt.trees]).reshape(-1, 3)
    diam = np.array([t.diameter_m for t in gt.trees])
    sil, band, off, views, failed = [], [], [], [], []
    for lm in sm.trunks:
        if lm.band is None or lm.band_points is None:
            continue
        c = lm.band.cylinder
        centre = c.origin + ((lm.band_points.mean(0) - c.origin) @ c.axis) * c.axis  # (3,) odom, the band's middle
        planes: list[TangentPlane] = []
        both = 0
        for o in lm.observations:
            T = sm.keyframe_poses[o.keyframe]
            ends = transform_points(np.linalg.inv(T), np.stack([centre - half * lm.axis, centre + half * lm.axis]))
            v = intr.fy * ends[:, 1] / ends[:, 2] + intr.cy  # (2,) px, the band's rows in this view
            p = outline_planes(np.asarray(o.detection.mask), T, intr, (int(np.ceil(v.min())), int(np.floor(v.max()))),
                               o.keyframe)
            both += len(p) == 2
            planes += p
        try:
            cyl, _ = cylinder_from_silhouettes(planes, (-half, half), origin_hint=centre, up=lm.axis)
        except CylinderError as err:
            failed.append(f"trunk {lm.id}: {err}")
            continue
        # placed by the true pose of the keyframe that saw the band best: the side's own drift left out
        kb = max(lm.observations, key=lambda o: o.band_pixels).keyframe
        w = transform_points(true_pose[kb] @ np.linalg.inv(sm.keyframe_poses[kb]), cyl.origin[None])[0]
        k = int(np.argmin(np.linalg.norm(base[:, :2] - w[:2], axis=1)))
        a = (top[k] - base[k]) / np.linalg.norm(top[k] - base[k])
        d = w - base[k]
        off.append(1000 * float(np.linalg.norm(d - (d @ a) * a)))
        sil.append(1000 * (2 * cyl.radius - diam[k]))
        band.append(1000 * ((lm.diameter_m if lm.diameter_m is not None else np.nan) - diam[k]))
        views.append(both)
    s, b = np.array(sil), np.array(band)
    return {"trunks": len(sil), "failed": failed, "views_median": float(np.median(views)) if views else None,
            "silhouette_mae_mm": float(np.abs(s).mean()) if len(s) else None,
            "silhouette_bias_mm": float(s.mean()) if len(s) else None,
            "rgbd_band_mae_mm": float(np.nanmean(np.abs(b))) if len(b) else None,
            "axis_off_median_mm": float(np.median(off)) if off else None,
            "axis_off_max_mm": float(np.max(off)) if off else None}


def _f(v: float | None, d: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{d}f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_case_arguments(ap)
    ap.add_argument("--half", type=float, default=0.08, help="m, half the band's length along the trunk")
    args = ap.parse_args(argv)
    rows = []
    for sc in args.scenarios:
        gt, sides = case_sides(sc, args)
        for side in ("front", "back"):
            rows.append({"scenario": sc, "side": side, **_side_rows(sides[side], gt, side, args.half)})
            print(json.dumps(rows[-1]), file=sys.stderr)
    tab = Table(title=f"trunk cylinders from silhouettes only ({'exact' if args.masks else 'detector'} masks, "
                      f"band +-{args.half:g} m, the RGB-D sides' poses), {args.trees} trees, {args.rate:g} Hz, "
                      f"seed {args.seed}")
    for col in ("scenario", "side", "trunks", "views (median)", "silhouette diam MAE / bias mm",
                "RGB-D band diam MAE mm", "silhouette axis off true, median / max mm"):
        tab.add_column(col, justify="right")
    for r in rows:
        tab.add_row(r["scenario"], r["side"], str(r["trunks"]), _f(r["views_median"], 0),
                    f"{_f(r['silhouette_mae_mm'])} / {_f(r['silhouette_bias_mm'])}", _f(r["rgbd_band_mae_mm"]),
                    f"{_f(r['axis_off_median_mm'], 1)} / {_f(r['axis_off_max_mm'], 1)}")
    Console(width=160).print(tab)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.json.with_suffix(".partial")
        tmp.write_text(portable_json(rows, indent=1))
        tmp.replace(args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
