"""Benchmark: the two-side merge side by side with its baselines on the same reconstructed sides.

For each scenario: simulate a row (or reuse it), reconstruct both sides with their trunks once (the
default configuration: trunks from the shipped detector), then merge them with each `merge.method`
(semantic_ba, the same without the trellis posts, initial, icp) and print one table: time per step, trunk pairs, the gap between the two
sides' trunk axes at the diameter height (median / max), the rigid merge error against the truth at
the trunk bases (rotation, mean translation), the merged map's error (eval.metrics.map_merge_error) with
all keyframes and with each side's trunk-seeing sweep only (on a two-sweep path the raised sweep sees no
trunk, and on long rows its drift against the level sweep dominates the first), tree positions in map (mean distance, RMSE after one
rigid alignment) and the trunk diameter MAE of the trees; on the trees both sides measured, the two-side
diameter's MAE beside each side's own.

Usage:
  python benchmarks/merge.py [--scenarios standard slope_weeds] [--trees 10] [--rate 15] [--seed 0]
        [--workdir /tmp/merge_bench] [--reuse] [--json out.json] [--tile 3 10] [--repeat 5] [--masks]
        [--sim-set trunk.ellipticity=[0.03,0.1] --tag ellip] [--methods semantic_ba initial]
        [--variant depth3:semantic_ba.trunk_sigma_depth_m=0.003,semantic_ba.height_sigma_m=0]

Long rows: --tile K also merges the reconstructed sides repeated K times along the row (a 100-tree
row from a 10-tree one: --trees 10 --tile 10), timed the same way; a simulated 30-tree row takes about
40 minutes to render on 2 cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from orchard_mapping.config import load_config, parse_sets, unflatten  # noqa: E402
from orchard_mapping.core.geometry import matrix_to_quat, transform_points  # noqa: E402
from orchard_mapping.core.types import StampedTrajectory  # noqa: E402
from orchard_mapping.eval.evaluate import trunk_scene_points  # noqa: E402
from orchard_mapping.eval.ground_truth import load_ground_truth  # noqa: E402
from orchard_mapping.eval.metrics import map_merge_error, merge_error, rigid_rmse_mm, trajectory_between  # noqa: E402
from orchard_mapping.io.results import portable_json
from orchard_mapping.pipeline import Timings, map_poses, merge_sides, open_sides, reconstruct_side, two_side_trees  # noqa: E402
from orchard_mapping.sim.scenario import load_scenario  # noqa: E402
from orchard_mapping.sim.simulate import simulate  # noqa: E402

METHODS = ("semantic_ba", "semantic_ba_no_posts", "initial", "icp")
# method label -> config overrides (a label that is not a merge.method is a variant of one)
VARIANTS = {"semantic_ba_no_posts": {"merge": {"method": "semantic_ba"}, "semantic_ba": {"use_posts": False}}}


def _sides(sim_dir: Path, reuse: bool, masks: bool = False) -> dict[str, Any]:
    """Both sides reconstructed with their trunks (from the shipped detector, or with `masks` the simulator's
    exact instance masks); kept in sides.pkl (sides_masks.pkl) beside the simulation for --reuse."""
    cache = sim_dir.parent / ("sides_masks.pkl" if masks else "sides.pkl")
    if reuse and cache.is_file():
        with cache.open("rb") as f:
            return pickle.load(f)
    cfg = load_config(overrides={"trunks": {"source": "masks", "masks_dir": str(sim_dir / "masks")}} if masks else None)
    seqs = open_sides(sim_dir / "front", sim_dir / "back", cfg)
    sides = {side: reconstruct_side(seq, side, cfg, Timings()) for side, seq in seqs.items()}
    tmp = cache.with_suffix(".partial")
    with tmp.open("wb") as f:
        pickle.dump(sides, f, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(cache)
    return sides


def add_case_arguments(ap: argparse.ArgumentParser) -> None:
    """The options that name a simulated case and its reconstructed sides (shared by the benchmarks that
    reuse this one's cache)."""
    ap.add_argument("--scenarios", nargs="+", default=["standard", "slope_weeds"])
    ap.add_argument("--trees", type=int, default=10)
    ap.add_argument("--rate", type=float, default=15.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "merge_bench")
    ap.add_argument("--reuse", action="store_true",
                    help="skip simulating (and reconstructing: sides.pkl) when the case folder holds them")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--masks", action="store_true",
                    help="trunks from the simulator's exact instance masks instead of the shipped detector")
    ap.add_argument("--sim-set", action="append", default=[], metavar="KEY=VALUE",
                    help="scenario setting for the rows simulated here (e.g. 'trunk.ellipticity=[0.03,0.1]'), "
                         "named in --tag")
    ap.add_argument("--tag", default="", help="added to the simulated rows' folder names (their settings)")


def case_sides(scenario: str, args: argparse.Namespace) -> tuple[Any, dict[str, Any]]:
    """(ground truth, both sides reconstructed with their trunks) of one scenario (add_case_arguments)."""
    name = f"{scenario}_{args.trees}trees_{args.rate:g}hz_seed{args.seed}" + (f"_{args.tag}" if args.tag else "")
    sim_dir = args.workdir / name / "sim"
    if not (args.reuse and (sim_dir / "ground_truth.json").is_file()):
        settings = {"row.n_trees": args.trees, "camera.rate_hz": args.rate, **parse_sets(args.sim_set)}
        simulate(load_scenario(scenario, settings), args.seed, sim_dir, force=True)
    return load_ground_truth(sim_dir / "ground_truth.json"), _sides(sim_dir, args.reuse, args.masks)


def _shift_transform(T: np.ndarray, d: np.ndarray) -> np.ndarray:
    out = np.array(T, float, copy=True)
    out[..., :3, 3] += d
    return out


def _tiled_side(sm: Any, copies: int, shift: np.ndarray, diameter_offset: np.ndarray) -> Any:
    """The side map of a row `copies` times as long: the reconstructed side repeated every `shift` (3,) m
    (odom), keyframes, cloud, trunks (with their grounds, band points and views) and posts moved along. What the
    merge reads, not what a longer recording would give (the copies' drifts repeat): for its time and
    memory on long rows without rendering them. diameter_offset (copies, T) m is added to each copy's
    trunk diameters: exact copies would pair as well one copy off as in place (the alignment tells trees
    apart by their diameters, as in a real row)."""
    K, n = len(sm.keyframe_poses), len(sm.trunks)
    dur = float(sm.keyframe_stamps[-1] - sm.keyframe_stamps[0]) + 1.0
    poses, stamps, clouds, colours, trunks, posts = [], [], [], [], [], []
    for c in range(copies):
        d = c * shift
        poses.append(_shift_transform(sm.keyframe_poses, d))
        stamps.append(sm.keyframe_stamps + c * dur)
        clouds.append(sm.cloud_points + d.astype(sm.cloud_points.dtype))
        colours.append(sm.cloud_colors)
        for t in sm.trunks:
            g = t.ground
            if g is not None:
                g = dataclasses.replace(g, point=g.point + d, offset=g.offset - float(g.normal @ d))
            band = t.band
            if band is not None:
                band = dataclasses.replace(band, cylinder=dataclasses.replace(band.cylinder, origin=band.cylinder.origin + d))
            dd = float(diameter_offset[c, t.id])
            trunks.append(dataclasses.replace(
                t, id=t.id + c * n, base=t.base + d, ground=g, band=band,
                diameter_m=None if t.diameter_m is None else t.diameter_m + dd,
                band_points=None if t.band_points is None else t.band_points + d,
                band_views=[dataclasses.replace(v, T_odom_cam=_shift_transform(v.T_odom_cam, d)) for v in t.band_views],
                observations=[dataclasses.replace(o, keyframe=o.keyframe + c * K) for o in t.observations]))
        posts += [dataclasses.replace(p, id=p.id + c * len(sm.posts), place=p.place + d, observations=[
            dataclasses.replace(o, keyframe=o.keyframe + c * K) for o in p.observations]) for p in sm.posts]
    return dataclasses.replace(sm, keyframe_poses=np.concatenate(poses), keyframe_stamps=np.concatenate(stamps),
                               cloud_points=np.concatenate(clouds), cloud_colors=np.concatenate(colours),
                               trunks=trunks, posts=posts,
                               odometry_poses=None if sm.odometry_poses is None else np.concatenate(
                                   [_shift_transform(sm.odometry_poses, c * shift) for c in range(copies)]))


def _tiled(sides: dict[str, Any], gt: Any, copies: int) -> tuple[dict[str, Any], Any]:
    """Sides and truth of the row repeated `copies` times along the row, one tree spacing apart (and up
    its slope: the copies continue the ground)."""
    P = np.array([t.position for t in gt.trees])
    P = P[np.argsort(P[:, 0])]  # along world x, the row
    step_world = (P[-1] - P[0]) * len(P) / (len(P) - 1)  # the row plus one spacing
    # Each copy's trees get their own diameters (the first copy keeps the true ones): offsets drawn like
    # the simulator's trees differ (sd 8.5 mm), per true tree, applied to both sides' trunks of that tree.
    rng = np.random.default_rng(0)
    tree_offset = np.vstack([np.zeros(len(gt.trees)), rng.normal(0.0, 0.0085, (copies - 1, len(gt.trees)))])
    out = {}
    for side, sm in sides.items():
        T_odom_world = np.linalg.inv(gt.sides[side].T_world_odom)
        true_bases = transform_points(T_odom_world, np.array([t.trunk_base for t in gt.trees]))
        nearest = [int(np.argmin(np.linalg.norm(true_bases - t.base, axis=1))) for t in sm.trunks]
        offset = np.zeros((copies, max([t.id for t in sm.trunks], default=-1) + 1))
        for t, k in zip(sm.trunks, nearest, strict=True):
            offset[:, t.id] = tree_offset[:, k]
        # Each side's copies continue along that side's own estimate of the row (the line through its trunk
        # bases), not the true row: repeated in the true direction, the two sides' small relative heading
        # (0.4 deg on this row) would come back at every copy as a saw tooth no rigid merge can follow;
        # along its own line it grows steadily along the row, as a longer recording's would.
        B = np.array([t.base for t in sm.trunks])
        u = np.linalg.svd(B - B.mean(axis=0), full_matrices=False)[2][0]
        u = u if (gt.sides[side].T_world_odom[:3, :3] @ u) @ step_world > 0 else -u
        out[side] = _tiled_side(sm, copies, float(np.linalg.norm(step_world)) * u, offset)
    trees = tuple(dataclasses.replace(t, id=t.id + c * len(gt.trees), position=t.position + c * step_world,
                                      trunk_base=t.trunk_base + c * step_world, trunk_top=t.trunk_top + c * step_world,
                                      diameter_m=t.diameter_m + float(tree_offset[c, k]))
                  for c in range(copies) for k, t in enumerate(gt.trees))
    return out, dataclasses.replace(gt, trees=trees)


def _score(method: str, sides: dict[str, Any], gt: Any, repeat: int = 1) -> dict[str, Any]:
    """One merge scored against the truth; with repeat > 1 the merge is run that many times and its time (and
    each step's) is the median (the scores are those of the last run: the merge is deterministic)."""
    cfg = load_config(overrides=VARIANTS.get(method, {"merge": {"method": method}}))
    runs = []
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        m = merge_sides(sides["front"], sides["back"], cfg)
        runs.append((time.perf_counter() - t0, m.seconds))
    seconds = float(np.median([r[0] for r in runs]))
    steps = {k: float(np.median([r[1][k] for r in runs])) for k in runs[-1][1]}
    trees = two_side_trees(m, sides, cfg)
    T_back_world = np.linalg.inv(gt.sides["back"].T_world_odom)
    bases = transform_points(T_back_world, np.array([t.trunk_base for t in gt.trees]).reshape(-1, 3))
    me = merge_error(m.T_front_back, gt.T_front_back, bases)
    in_map = {side: StampedTrajectory(sides[side].keyframe_stamps, P[:, :3, 3], matrix_to_quat(P[:, :3, :3]))
              for side, P in map_poses(m, sides).items()}
    mm = map_merge_error(in_map["front"], in_map["back"], gt.sides["front"].trajectory, gt.sides["back"].trajectory,
                         gt.sides["front"].T_world_odom, gt.sides["back"].T_world_odom,
                         np.array([t.trunk_base for t in gt.trees]).reshape(-1, 3),
                         scene_points=trunk_scene_points(gt))
    # The same error with each side fitted on its trunk-seeing sweep only (its keyframes from the first to the
    # last trunk observation, as the evaluator's merge.map_trunk_sweep): what the merge itself got right, the
    # side's other sweeps' drift left out.
    trunk_sweep = {}
    for side, tr in in_map.items():
        seen = [o.stamp for t in sides[side].trunks for o in t.observations]
        trunk_sweep[side] = trajectory_between(tr, min(seen), max(seen)) if seen else tr
    ms = map_merge_error(trunk_sweep["front"], trunk_sweep["back"], gt.sides["front"].trajectory,
                         gt.sides["back"].trajectory, gt.sides["front"].T_world_odom, gt.sides["back"].T_world_odom,
                         np.array([t.trunk_base for t in gt.trees]).reshape(-1, 3), scene_points=trunk_scene_points(gt))
    T_front_world = np.linalg.inv(gt.sides["front"].T_world_odom)
    true_xyz = transform_points(T_front_world, np.array([t.position for t in gt.trees]).reshape(-1, 3))
    est = np.array([t.position for t in trees], float).reshape(-1, 3)
    near = np.argmin(np.linalg.norm(est[:, None] - true_xyz[None], axis=2), axis=1) if len(est) else np.zeros(0, int)
    dist = np.linalg.norm(est - true_xyz[near], axis=1) if len(est) else np.zeros(0)
    ok = dist < 0.3
    rmse = rigid_rmse_mm(est[ok], true_xyz[near[ok]])
    d_err = [1000 * (t.trunk_diameter_m - gt.trees[k].diameter_m) for t, k, o in zip(trees, near, ok, strict=True)
             if o and t.trunk_diameter_m is not None]
    # The two-side diameter against each side's own, on the trees both sides measured (mm, MAE)
    both = [(t, k) for t, k, o in zip(trees, near, ok, strict=True) if o and t.trunk_diameter_m is not None and t.per_side
            and all((t.per_side.get(sd) or {}).get("diameter_m") is not None for sd in ("front", "back"))]

    def mae(get: Any) -> float | None:
        return float(np.mean([abs(1000 * (get(t) - gt.trees[k].diameter_m)) for t, k in both])) if both else None
    gaps = m.sba.gaps_after_mm if m.sba is not None else None
    return {
        "method": method, "seconds": seconds, "steps": steps, "repeats": len(runs), "pairs": len(m.pairs),
        "gap_median_mm": float(np.median(list(gaps.values()))) if gaps else None,
        "gap_max_mm": float(max(gaps.values())) if gaps else None,
        "rotation_error_deg": me.rotation_error_deg, "translation_error_mm": me.translation_error_mm,
        "map_rotation_error_deg": mm.rotation_error_deg, "map_translation_error_mm": mm.translation_error_mm,
        "map_translation_max_mm": mm.max_translation_error_mm,
        "trunk_sweep_map_rotation_error_deg": ms.rotation_error_deg,
        "trunk_sweep_map_translation_error_mm": ms.translation_error_mm,
        "trees": len(trees), "trees_matched": int(ok.sum()),
        "tree_distance_mean_mm": float(1000 * dist[ok].mean()) if ok.any() else None,
        "tree_position_rmse_mm": rmse,
        "diameter_mae_mm": float(np.mean(np.abs(d_err))) if d_err else None,
        "diameter_both_sides_n": len(both),
        "diameter_both_sides_mae_mm": {"two_side": mae(lambda t: t.trunk_diameter_m),
                                       "front": mae(lambda t: t.per_side["front"]["diameter_m"]),
                                       "back": mae(lambda t: t.per_side["back"]["diameter_m"])},
    }


def _f(v: float | None, d: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{d}f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_case_arguments(ap)
    ap.add_argument("--tile", type=int, nargs="*", default=[],
                    help="also merge the reconstructed sides repeated K times along the row (long rows without "
                         "rendering them: time and memory), e.g. --tile 3 10")
    ap.add_argument("--tile-methods", nargs="+", default=["semantic_ba"], help="merge methods for the tiled rows")
    ap.add_argument("--repeat", type=int, default=1,
                    help="time each merge of the tiled rows (and of the row itself) this many times: the median "
                         "is reported (these machines are noisy: one run's 100 / 30 ratio moved 3.2-4.1x)")
    ap.add_argument("--variant", action="append", default=[], metavar="LABEL:KEY=VALUE[,KEY=VALUE]",
                    help="also merge with semantic_ba under these settings, e.g. "
                         "'depth3:semantic_ba.trunk_sigma_depth_m=0.003' or 'no_anchor:semantic_ba.height_sigma_m=0'")
    ap.add_argument("--methods", nargs="+", default=list(METHODS), help="merge methods for the rows themselves")
    args = ap.parse_args(argv)
    methods = list(args.methods)
    for spec in args.variant:
        label, _, sets = spec.partition(":")
        VARIANTS[label] = unflatten({"merge.method": "semantic_ba", **parse_sets(list(filter(None, sets.split(","))))})
        methods.append(label)
    rows = []
    for sc in args.scenarios:
        gt, sides = case_sides(sc, args)
        for copies in [1, *args.tile]:
            s_k, gt_k = (sides, gt) if copies == 1 else _tiled(sides, gt, copies)
            for method in methods if copies == 1 else args.tile_methods:
                label = sc if copies == 1 else f"{sc} x{copies}"
                rows.append({"scenario": label, "trees_in_row": args.trees * copies, **_score(method, s_k, gt_k, args.repeat if method in args.tile_methods else 1)})
                print(json.dumps(rows[-1]), file=sys.stderr)
    tab = Table(title=f"two-side merge, {args.trees} trees (x K: tiled), {args.rate:g} Hz, seed {args.seed} (same sides for every method)")
    for col in ("scenario", "method", "s", "align / init / SBA s", "pairs", "axis gap mm med/max", "rot err deg", "transl err mm", "map rot deg", "map transl mm",
                "trunk sweep: map rot / transl",
                "trees matched", "tree dist mm", "tree RMSE mm", "diam MAE mm", "diam MAE both sides: 2-side/front/back (n)"):
        tab.add_column(col, justify="right")
    for r in rows:
        st = r["steps"]
        tab.add_row(r["scenario"], r["method"], _f(r["seconds"]),
                    " / ".join(_f(st.get(k)) for k in ("alignment", "initial_transform", "semantic_ba")), str(r["pairs"]),
                    f"{_f(r['gap_median_mm'], 1)}/{_f(r['gap_max_mm'], 1)}", _f(r["rotation_error_deg"], 3),
                    _f(r["translation_error_mm"], 1), _f(r.get("map_rotation_error_deg"), 3),
                    _f(r.get("map_translation_error_mm"), 1),
                    f"{_f(r.get('trunk_sweep_map_rotation_error_deg'), 3)} / "
                    f"{_f(r.get('trunk_sweep_map_translation_error_mm'), 1)}", f"{r['trees_matched']}/{r['trees']}",
                    _f(r["tree_distance_mean_mm"], 1), _f(r["tree_position_rmse_mm"], 1), _f(r["diameter_mae_mm"]),
                    "/".join(_f(r["diameter_both_sides_mae_mm"][k]) for k in ("two_side", "front", "back"))
                    + f" ({r['diameter_both_sides_n']})")
    Console(width=200).print(tab)
    # The long-row goal: the merge of the longest tiled row against the shortest, the same method, one run
    for sc in args.scenarios:
        for method in args.tile_methods:
            tiled = sorted((r for r in rows if r["method"] == method and r["scenario"].startswith(f"{sc} x")),
                           key=lambda r: r["trees_in_row"])
            if len(tiled) >= 2:
                a, b = tiled[0], tiled[-1]
                print(f"{sc} {method}: {b['trees_in_row']} / {a['trees_in_row']} tiled trees: whole merge "
                      f"{b['seconds'] / a['seconds']:.2f}x ({_f(b['seconds'])} / {_f(a['seconds'])} s, median of "
                      f"{a['repeats']}), " + ", ".join(
                          f"{k} {b['steps'][k] / a['steps'][k]:.2f}x" for k in a["steps"] if a["steps"][k] > 0))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(portable_json(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
