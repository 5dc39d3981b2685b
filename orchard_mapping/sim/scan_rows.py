"""Rows of real laser-scanned trees, rendered by the point-splatting renderer (`sim/splat.py`).

An evaluation domain the product is never trained or tuned on (benchmarks/unseen_rows.py): trees are
real TLS scans (benchmarks/data/real_trees/, scaled to orchard size), the ground, posts, wire and the
neighbouring rows are sampled points, and the frames come from a renderer and sensor model of their own.
Only the camera paths (sim/trajectory.py), the bag writer and the ground-truth schema are shared with
the simulator (`orchard-map evaluate` reads the result).

Truth is computed from the scene's own points here: trunk cylinders by slicing the full 360-degree scan
and fitting an algebraic circle per slice (written here, no `orchard_mapping.core` estimator), local
ground planes from the terrain function, what each side saw from the renderer's per-pixel buffers.
Canopy volume (0.0: not stated, the evaluator skips it) is left out; fruit only where the spec places them
(`ScanRowSpec.fruit_per_tree`), each with its own visibility per side (the simulator's rule).

The scene (scans, placement, trunk truth by slicing) is built in sim/scan_row_scene.py; here it is rendered,
recorded and its truth written.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from orchard_mapping.config import TopicsConfig
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.io.bag_writer import BagWriter
from orchard_mapping.io.results import atomic_write_text
from orchard_mapping.sim.scan_row_scene import (
    GROUND_CELL_M,
    LOCAL_GROUND_RADIUS_M,
    PlacedTree,
    ScanRowScene,
    ScanRowSpec,
    build_scan_row,
    load_scan_trees,
    local_ground_plane,
)
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.simulate import fresh_output_folder
from orchard_mapping.sim.splat import PCls, SplatFrame, SplatRenderer, StereoSensor
from orchard_mapping.sim.trajectory import CameraPath, side_path
from orchard_mapping.sim.truth import fruit_disc_fraction, fruit_visible

log = logging.getLogger(__name__)

__all__ = ["ScanRowResult", "generate_scan_row"]

SCHEMA = "orchard_mapping.ground_truth/1"
T0_FRONT = 1_700_000_000.0
SIDE_GAP_S = 60.0
DIAMETER_HEIGHT_M = 0.30
# What a side saw (the simulator's visibility definitions, docs/ground_truth.md, applied to splat buffers)
TRUNK_MIN_PIXELS = 50
TOP_BAND_M = 0.10
GROUND_SEEN_MAX_RANGE_M = 2.5
GROUND_MIN_CELLS = 50
GROUND_MIN_FRAMES = 5

Progress = Callable[[str, int, int], None]


# ----------------------------------------------------------------------------------------------- visibility
class SplatVisibility:
    """What one side saw of each tree, from the splat renderer's per-pixel class / instance / point buffers
    (the simulator's visibility definitions, docs/ground_truth.md)."""

    def __init__(self, row: ScanRowScene) -> None:
        self.row = row
        n = len(row.trees)
        self.gp = np.array([t.ground_point for t in row.trees]).reshape(n, 3)
        self.gn = np.array([t.ground_normal for t in row.trees]).reshape(n, 3)
        self.height = np.array([t.height for t in row.trees])
        self.trunk_px = np.zeros(n, np.int64)
        self.top_seen = np.zeros(n, bool)
        self.point_seen = np.zeros(len(row.points.xyz), bool)
        n_c = int(round(2 * LOCAL_GROUND_RADIUS_M / GROUND_CELL_M))
        self.cells = np.zeros((n, n_c, n_c), np.int32)
        self.fruit_pos = np.array([f.position for f in row.fruit]).reshape(-1, 3)
        self.fruit_r = np.array([f.radius for f in row.fruit])
        self.fruit_seen = np.zeros(len(row.fruit), bool)

    def add(self, f: SplatFrame, T_world_cam: np.ndarray, K: CameraIntrinsics) -> None:
        cls, inst = f.cls.ravel(), f.inst.ravel()
        if len(self.fruit_pos):  # visible pixels over the projected disc (the simulator's rule)
            counts = np.bincount(inst[cls == PCls.FRUIT], minlength=len(self.fruit_pos))
            frac = fruit_disc_fraction(counts, self.fruit_pos, self.fruit_r, T_world_cam, K.fx)
            self.fruit_seen |= fruit_visible(frac, counts)
        idx = f.index.ravel()
        self.point_seen[idx[idx >= 0]] = True
        pts = f.points.reshape(-1, 3)
        g = (cls == PCls.GROUND) & (f.depth.ravel() > 0) & (f.depth.ravel() <= GROUND_SEEN_MAX_RANGE_M)
        gpts = pts[g]
        n_c = self.cells.shape[1]
        for t in range(len(self.gp)):
            d = gpts[:, :2] - self.gp[t, :2]
            d = d[np.sum(d * d, 1) < LOCAL_GROUND_RADIUS_M**2]
            if len(d):
                ij = np.unique(np.clip(((d + LOCAL_GROUND_RADIUS_M) / GROUND_CELL_M).astype(int), 0, n_c - 1), axis=0)
                self.cells[t, ij[:, 0], ij[:, 1]] += 1
        sel = ((cls == PCls.TRUNK) | (cls == PCls.FOLIAGE)) & (inst >= 0)
        if not sel.any():
            return
        tid = inst[sel]
        h = np.sum((pts[sel] - self.gp[tid]) * self.gn[tid], axis=1)
        band = (cls[sel] == PCls.TRUNK) & (np.abs(h - DIAMETER_HEIGHT_M) < 0.05)
        self.trunk_px = np.maximum(self.trunk_px, np.bincount(tid[band], minlength=len(self.trunk_px)))
        self.top_seen[np.unique(tid[h >= self.height[tid] - TOP_BAND_M])] = True

    def summary(self, t: PlacedTree, offset: int, foliage: np.ndarray) -> dict:
        seen = self.point_seen[offset:offset + len(t.points)][foliage]
        i, j = np.nonzero(self.cells[t.id] >= GROUND_MIN_FRAMES)
        lg = None
        if len(i) >= GROUND_MIN_CELLS:
            cx = t.ground_point[0] - LOCAL_GROUND_RADIUS_M + (i + 0.5) * GROUND_CELL_M
            cy = t.ground_point[1] - LOCAL_GROUND_RADIUS_M + (j + 0.5) * GROUND_CELL_M
            p, nrm = local_ground_plane(self.row.ground, float(t.ground_point[0]), float(t.ground_point[1]),
                                   np.column_stack([cx, cy]))
            disk = np.pi * LOCAL_GROUND_RADIUS_M**2 / GROUND_CELL_M**2
            lg = {"point": np.round(p, 5).tolist(), "normal": np.round(nrm, 6).tolist(),
                  "seen_fraction": round(min(1.0, len(i) / disk), 4)}
        return {"trunk_at_diameter_height": bool(self.trunk_px[t.id] >= TRUNK_MIN_PIXELS),
                "top": bool(self.top_seen[t.id]),
                "canopy_fraction": round(float(seen.mean()) if seen.size else 0.0, 4),
                "local_ground": lg}


# ----------------------------------------------------------------------------------------------- recording
@dataclass(frozen=True)
class ScanRowResult:
    out_dir: Path
    bags: dict[str, Path]
    truth_path: Path
    frames: dict[str, int]
    render_s: float


def _tum(path: CameraPath, T_world_odom: np.ndarray) -> list[list[float]]:
    T = np.linalg.inv(T_world_odom)[None] @ path.poses
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()
    return [[round(float(s), 6), *map(float, p), *map(float, qq)] for s, p, qq in zip(path.stamps, T[:, :3, 3], q, strict=True)]


def _image_motion(Tp: np.ndarray, Tc: np.ndarray, K: CameraIntrinsics, depth: float = 1.5) -> tuple[float, float]:
    """Pixel motion of the point `depth` m ahead of the current camera's centre between the two poses."""
    p = Tc[:3, :3] @ np.array([0.0, 0.0, depth]) + Tc[:3, 3]
    q = np.linalg.inv(Tp)[:3, :3] @ p + np.linalg.inv(Tp)[:3, 3]
    if q[2] <= 0.05:
        return 0.0, 0.0
    return float(K.fx * q[0] / q[2] + K.cx - K.cx), float(K.fy * q[1] / q[2] + K.cy - K.cy)


def _tree_truth(row: ScanRowScene, vis: dict[str, SplatVisibility], recorded: tuple[str, ...]) -> list[dict]:
    out = []
    offset = 0
    for t in row.trees:
        sl = t.slices
        h_gn = (sl.centres - t.ground_point) @ t.ground_normal  # slice heights above the local ground

        def diam_at(h: float, half: float = 0.04) -> float:
            m = np.abs(h_gn - h) <= half  # noqa: B023 - diam_at() is called within this iteration only
            if m.sum() < 2:
                m = np.argsort(np.abs(h_gn - h))[:3]  # noqa: B023 - as above
                m = np.isin(np.arange(len(h_gn)), m)  # noqa: B023 - as above
            c = np.polyfit(h_gn[m], 2 * sl.radii[m], 1)  # noqa: B023 - as above
            return float(np.polyval(c, h))

        top = t.base + t.axis * (t.clear_height / float(t.axis @ t.ground_normal))
        foliage = ~t.trunk
        obs = {}
        for side in ("front", "back"):
            obs[side] = vis[side].summary(t, offset, foliage) if side in recorded else {}
        fruit = []
        fv = {"front": 0, "back": 0, "either": 0, "both": 0}
        for gi, fr in enumerate(row.fruit):
            if fr.tree != t.id:
                continue
            v = {side: bool(side in recorded and vis[side].fruit_seen[gi]) for side in ("front", "back")}
            fruit.append({"id": gi, "position": np.round(fr.position, 5).tolist(), "radius_m": round(fr.radius, 5),
                          "color": fr.color, "visible": v})
            fv["front"] += v["front"]
            fv["back"] += v["back"]
            fv["either"] += v["front"] or v["back"]
            fv["both"] += v["front"] and v["back"]
        out.append({
            "id": t.id,
            "position": np.round(t.base, 5).tolist(),
            "scan": t.scan,
            "scale": round(t.scale, 5),
            "trunk": {
                "base": np.round(t.base, 5).tolist(), "top": np.round(top, 5).tolist(),
                "axis": np.round(t.axis, 6).tolist(),
                "diameter_m": round(diam_at(DIAMETER_HEIGHT_M), 5),
                "base_diameter_m": round(diam_at(0.06), 5),
                "top_diameter_m": round(diam_at(min(t.clear_height, float(h_gn.max()))), 5),
                "clear_height_m": round(t.clear_height, 4),
            },
            "local_ground": {"point": np.round(t.ground_point, 5).tolist(),
                             "normal": np.round(t.ground_normal, 6).tolist()},
            "height_m": round(t.height, 4),
            "canopy_volume_m3": 0.0,
            "fruit": fruit,
            "fruit_count": len(fruit),
            "fruit_visible": fv,
            "observed": obs,
        })
        offset += len(t.points)
    return out


def generate_scan_row(out_dir: str | Path, *, seed: int = 0, spec: ScanRowSpec = ScanRowSpec(),
                      data_dir: str | Path | None = None, force: bool = False, progress: Progress | None = None,
                      topics: TopicsConfig = TopicsConfig(), record: tuple[str, ...] = ("front", "back")
                      ) -> ScanRowResult:
    """Build a row of real scanned trees, render both sides with the splat renderer and write OUT/front,
    OUT/back (rosbag2 MCAP) and OUT/ground_truth.json (schema orchard_mapping.ground_truth/1).
    Raises ScanDataError when the scan files are missing."""
    import time

    out = fresh_output_folder(out_dir, force, "force=True")
    trees = load_scan_trees(data_dir)
    row = build_scan_row(seed, spec, trees)
    K = CameraIntrinsics(spec.width, spec.height, spec.fx, spec.fy, spec.cx, spec.cy)
    sc = load_scenario(spec.motion, {"camera.rate_hz": spec.rate_hz, "row.margin_m": spec.margin_m,
                                     "camera.width": spec.width, "camera.height": spec.height})
    renderer = SplatRenderer(row.points, K)
    vis = {side: SplatVisibility(row) for side in ("front", "back")}
    path_rng = np.random.default_rng([seed, 1])
    paths: dict[str, CameraPath] = {}
    bags: dict[str, Path] = {}
    frames: dict[str, int] = {}
    t0 = T0_FRONT
    t_start = time.perf_counter()
    for k, side in enumerate(("front", "back")):
        paths[side] = side_path(sc, side, row.row_x, row.ground, path_rng, t0)  # type: ignore[arg-type]
        t0 = float(paths[side].stamps[-1]) + SIDE_GAP_S
        if side not in record:
            continue
        rng = np.random.default_rng([seed, 2 + k])
        sensor = StereoSensor(wb_gain=(rng.uniform(1.02, 1.1), 1.0, rng.uniform(0.82, 0.95)),
                              motion_blur_exposure=0.06)
        p = paths[side]
        with BagWriter(out / side) as bag:
            for i in range(len(p.stamps)):
                stamp = float(p.stamps[i])
                f = renderer.render(p.poses[i])
                blur = _image_motion(p.poses[max(i - 1, 0)], p.poses[i], K)
                color, depth = sensor.apply(f, K.fx, rng, blur)
                bag.write_camera_info(topics.camera_info, stamp, K)
                bag.write_color(topics.color, stamp, color, encoding="rgb8", frame_id=K.frame_id)
                bag.write_depth(topics.depth, stamp, depth, encoding="16UC1", frame_id=K.frame_id)
                vis[side].add(f, p.poses[i], K)
                if progress:
                    progress(side, i + 1, len(p.stamps))
        bags[side] = out / side
        frames[side] = len(p.stamps)
    render_s = time.perf_counter() - t_start
    T_world_odom = {side: paths[side].poses[0] for side in ("front", "back")}
    truth = {
        "schema": SCHEMA,
        "scenario": f"scan_rows/{spec.motion}",
        "seed": seed,
        "n_trees": len(row.trees),
        "diameter_height_m": DIAMETER_HEIGHT_M,
        "canopy_alpha_m": 0.8,
        "canopy_volume_definition": "not stated (0.0): real scanned trees, no canopy volume truth",
        "height_definition": "Highest scan point of the tree (its own scan, neighbours' crowns inside the cut "
                             "included) above the local ground plane, along its normal.",
        "diameter_definition": "Trunk diameter at diameter_height_m above the local ground plane: algebraic "
                               "circle fits to 2 cm slices of the full 360-degree scan perpendicular to the "
                               "fitted axis, a line through the fitted diameters within 4 cm of that height.",
        "camera": {"width": K.width, "height": K.height, "fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy,
                   "rate_hz": spec.rate_hz, "depth_sigma_coeff": round(StereoSensor().depth_sd(1.0, K.fx), 6)},
        "trees": _tree_truth(row, vis, record),
        "posts": row.posts,
        "sides": {
            side: {
                "frame": f"odom_{side}", "bag": side, "recorded": side in record,
                "T_world_odom": np.round(T_world_odom[side], 9).tolist(),
                "path_length_m": round(paths[side].path_length_m, 4),
                "duration_s": round(float(paths[side].stamps[-1] - paths[side].stamps[0]), 4),
                "trajectory": _tum(paths[side], T_world_odom[side]),
            } for side in ("front", "back")
        },
        "T_front_back": np.round(np.linalg.inv(T_world_odom["front"]) @ T_world_odom["back"], 9).tolist(),
        "scan_row_spec": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(spec).items()},
        "scan_sources": sorted({s.source for s in trees}),
    }
    truth_path = out / "ground_truth.json"
    atomic_write_text(truth_path, json.dumps(truth, indent=1))
    log.info("scan row %s: %s frames, rendered in %.1f s", out, frames, render_s)
    return ScanRowResult(out, bags, truth_path, frames, render_s)
