"""Simulate recordings of an orchard row: bags per side, instance masks, ground_truth.json.

Output folder layout (docs/ground_truth.md):
  OUT/front/, OUT/back/       rosbag2 (MCAP) per side; `loop` mode writes one OUT/loop/ bag instead, `block`
                              mode one OUT/block/ bag (sim.block: OUT/row_<k>/ground_truth.json per row and
                              OUT/ground_truth.json for the block)
  OUT/ground_truth.json       the truth, from the scene description
  OUT/tree_surfaces.npz       the trees' surfaces as points with their tree id (per-point segmentation truth)
  OUT/masks/<side>/*.png      16-bit instance masks (trunks, fruit, posts) every `masks_every` frames
"""

from __future__ import annotations

import json
import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from orchard_mapping.config import TopicsConfig
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import ScenarioError
from orchard_mapping.io.bag_writer import BagWriter
from orchard_mapping.io.results import atomic_write_text
from orchard_mapping.sim.render import Renderer, RenderOutput, SensorModel
from orchard_mapping.sim.scenario import Scenario
from orchard_mapping.sim.scene import Cls, Scene, build_scene
from orchard_mapping.sim.trajectory import CameraPath, side_path
from orchard_mapping.sim.truth import (
    CANOPY_VOLUME_DEFINITION,
    DIAMETER_DEFINITION,
    HEIGHT_DEFINITION,
    TREE_SURFACES_NPZ,
    VisibilityAccumulator,
    alpha_complex_volume,
    diameter_at_height,
    tree_height,
    trunk_axis_at_height,
    write_tree_surfaces,
)

log = logging.getLogger(__name__)

SCHEMA = "orchard_mapping.ground_truth/1"
T0_FRONT = 1_700_000_000.0  # s, message time of the first front frame
SIDE_GAP_S = 60.0  # s between the end of the front recording and the start of the back one
MASK_TRUNK, MASK_FRUIT, MASK_POST = 1, 10000, 60000  # mask value offsets (docs/ground_truth.md)

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class SimulationResult:
    out_dir: Path
    bags: dict[str, Path]  # side (or "loop") -> bag folder
    truth_path: Path
    frames: dict[str, int]


def intrinsics_of(sc: Scenario) -> CameraIntrinsics:
    c = sc.camera
    return CameraIntrinsics(c.width, c.height, c.fx, c.fy, c.cx, c.cy)


@dataclass(frozen=True)
class Rig:
    """A scenario's scene with the camera that films it: what recording and tests share."""

    scene: Scene
    intrinsics: CameraIntrinsics
    renderer: Renderer
    sensor: SensorModel

    @staticmethod
    def build(sc: Scenario, seed: int) -> "Rig":
        scene = build_scene(sc, seed)
        intr = intrinsics_of(sc)
        return Rig(scene, intr, Renderer(scene, intr, seed), SensorModel.from_camera(sc.camera))

    def path(self, side: str, rng: np.random.Generator, t0: float = 0.0) -> CameraPath:
        """The scenario's camera path past `side` of the row (hand-held jitter drawn from rng)."""
        return side_path(self.scene.scenario, side, self.scene.row_x, self.scene.terrain, rng, t0)

    def shoot(self, T_world_cam: np.ndarray, rng: np.random.Generator, t: float = 0.0
              ) -> tuple[np.ndarray, np.ndarray, RenderOutput]:
        """(colour (H, W, 3) uint8, noisy depth (H, W) float32 m, the noise-free render) from a pose at time t."""
        out = self.renderer.render(T_world_cam, t)
        color, depth = self.sensor.apply(out, rng)
        return color, depth, out


def instance_mask(out: RenderOutput) -> np.ndarray:
    """(H, W) uint16: 0 background, 1 + tree id trunk, 10000 + fruit index, 60000 + post index."""
    m = np.zeros(out.cls.shape, np.uint16)
    inst = out.inst
    trunk = out.cls == Cls.TRUNK
    m[trunk] = MASK_TRUNK + inst[trunk]
    fruit = out.cls == Cls.FRUIT
    m[fruit] = MASK_FRUIT + inst[fruit]
    post = out.cls == Cls.POST
    m[post] = MASK_POST + inst[post]
    return m


def _tum(path: CameraPath, T_world_odom: np.ndarray) -> list[list[float]]:
    T_odom_world = np.linalg.inv(T_world_odom)
    T = T_odom_world[None] @ path.poses
    q = Rotation.from_matrix(T[:, :3, :3]).as_quat()  # x y z w
    return [[round(float(s), 6), *map(float, p), *map(float, qq)] for s, p, qq in zip(path.stamps, T[:, :3, 3], q, strict=True)]


def _record(scene: Scene, renderer: Renderer, sensor: SensorModel, path: CameraPath, bag_dir: Path,
            mask_dir: Path | None, masks_every: int, rng: np.random.Generator, acc: dict[str, VisibilityAccumulator],
            topics: TopicsConfig, label: str, progress: Progress | None, with_side_topic: bool,
            compress: bool = False, acc_keys: np.ndarray | None = None) -> None:
    """Render `path` into a bag (and masks). acc: what each frame saw, added to acc[its side] or, given
    acc_keys (N,), to acc[acc_keys[i]] (a block's passes)."""
    intr = renderer.K
    n = len(path.stamps)
    index_rows = []
    last_side = ""
    with BagWriter(bag_dir, compress=compress) as bag:
        for i in range(n):
            stamp = float(path.stamps[i])
            out = renderer.render(path.poses[i], stamp - float(path.stamps[0]))
            color, depth = sensor.apply(out, rng)
            side = str(path.sides[i])
            if with_side_topic and side != last_side:
                bag.write_string(topics.side, stamp, side)
                last_side = side
            bag.write_camera_info(topics.camera_info, stamp, intr)
            bag.write_color(topics.color, stamp, color, encoding="rgb8", frame_id=intr.frame_id)
            bag.write_depth(topics.depth, stamp, depth, encoding="16UC1", frame_id=intr.frame_id)
            acc[side if acc_keys is None else str(acc_keys[i])].add(out, path.poses[i])
            if mask_dir is not None and masks_every and i % masks_every == 0:
                cv2.imwrite(str(mask_dir / f"{i:06d}.png"), instance_mask(out))
                index_rows.append(f"{i},{stamp:.6f}")
            if progress:
                progress(label, i + 1, n)
    if mask_dir is not None and index_rows:
        (mask_dir / "index.csv").write_text("frame,stamp\n" + "\n".join(index_rows) + "\n")


def _tree_truth(scene: Scene, acc: dict[str, VisibilityAccumulator], alpha: float, dh: float,
                tree_ids: tuple[int, ...] | None = None) -> list[dict]:
    """The truth of each tree (of those in tree_ids; None: all), what acc["front"] and acc["back"] saw of it."""
    trees = []
    for tree in scene.trees:
        if tree_ids is not None and tree.id not in tree_ids:
            continue
        base = trunk_axis_at_height(tree, 0.0)
        top = trunk_axis_at_height(tree, tree.clear_height)
        axis = (top - base) / np.linalg.norm(top - base)
        fruit = []
        vis = {"front": 0, "back": 0, "either": 0, "both": 0}
        for gi in tree.fruit_index:
            f = scene.fruit[gi]
            v = {side: bool(acc[side].fruit_seen[gi]) for side in ("front", "back")}
            fruit.append({"id": int(gi), "position": np.round(f.position, 5).tolist(), "radius_m": round(f.radius, 5),
                          "color": f.color, "visible": v})
            vis["front"] += v["front"]
            vis["back"] += v["back"]
            vis["either"] += v["front"] or v["back"]
            vis["both"] += v["front"] and v["back"]
        trees.append({
            "id": tree.id,
            "position": np.round(base, 5).tolist(),
            "trunk": {
                "base": np.round(base, 5).tolist(), "top": np.round(top, 5).tolist(),
                "axis": np.round(axis, 6).tolist(),
                "diameter_m": round(diameter_at_height(tree, dh), 5),
                "base_diameter_m": round(diameter_at_height(tree, 0.0), 5),
                "top_diameter_m": round(diameter_at_height(tree, tree.clear_height), 5),
                "clear_height_m": round(tree.clear_height, 4),
            },
            "local_ground": {"point": np.round(tree.ground_point, 5).tolist(),
                             "normal": np.round(tree.ground_normal, 6).tolist()},
            "height_m": round(tree_height(tree), 4),
            "canopy_volume_m3": round(alpha_complex_volume(tree.canopy_points, alpha), 5),
            "fruit": fruit,
            "fruit_count": len(fruit),
            "fruit_visible": vis,
            "observed": {side: acc[side].summary(tree) for side in ("front", "back")},
        })
    return trees


def truth_document(sc: Scenario, seed: int, scene: Scene, acc: dict[str, VisibilityAccumulator],
                   paths: dict[str, CameraPath], T_world_odom: dict[str, np.ndarray], bag_of: dict[str, str],
                   recorded: dict[str, bool], tree_ids: tuple[int, ...] | None = None) -> dict:
    """ground_truth.json of one row filmed from both sides (docs/ground_truth.md): the trees (those in
    tree_ids; None: all) and what acc[side] saw of them, each side's path (paths[side], in its odom frame
    T_world_odom[side]), the bag it is in and whether it was recorded."""
    c = sc.camera
    dh = sc.trunk.diameter_height_m
    trees = _tree_truth(scene, acc, sc.canopy_alpha_m, dh, tree_ids)
    return {
        "schema": SCHEMA,
        "scenario": sc.name,
        "seed": seed,
        "n_trees": len(trees),
        "diameter_height_m": dh,
        "canopy_alpha_m": sc.canopy_alpha_m,
        "canopy_volume_definition": CANOPY_VOLUME_DEFINITION.format(alpha=sc.canopy_alpha_m),
        "height_definition": HEIGHT_DEFINITION,
        "diameter_definition": DIAMETER_DEFINITION,
        "camera": {"width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy,
                   "rate_hz": c.rate_hz, "depth_sigma_coeff": c.depth_sigma_coeff},
        "trees": trees,
        "posts": scene.posts,
        "sides": {
            side: {
                "frame": f"odom_{side}",
                "bag": bag_of[side],
                "recorded": recorded[side],
                "T_world_odom": np.round(T_world_odom[side], 9).tolist(),
                "path_length_m": round(paths[side].path_length_m, 4),
                "duration_s": round(float(paths[side].stamps[-1] - paths[side].stamps[0]), 4),
                "trajectory": _tum(paths[side], T_world_odom[side]),
            }
            for side in ("front", "back")
        },
        "T_front_back": np.round(np.linalg.inv(T_world_odom["front"]) @ T_world_odom["back"], 9).tolist(),
        "scenario_config": sc.model_dump(mode="json"),
    }


def fresh_output_folder(out_dir: str | Path, force: bool, how: str) -> Path:
    """The output folder of a simulation, created empty: a non-empty one is replaced only with force (`how` names
    the option that forces it), else ScenarioError."""
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        if not force:
            raise ScenarioError(f"output folder {out} exists and is not empty (use {how} to replace it)")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)
    return out


def simulate(sc: Scenario, seed: int, out_dir: str | Path, *, force: bool = False,
             topics: TopicsConfig = TopicsConfig(), progress: Progress | None = None,
             record: tuple[str, ...] = ("front", "back"), compress: bool = False) -> SimulationResult:
    """Render both sides of a row and write bags, masks and ground truth into out_dir.

    `record` limits which sides are rendered into bags (tests of one side's reconstruction): the
    ground truth keeps both sides' paths, and marks the side not recorded (`"recorded": false`; its
    visibility fields then say nothing). `compress`: zstd chunk compression of the MCAP bags.
    """
    out = fresh_output_folder(out_dir, force, "--force")
    if sc.path.mode == "block":
        from orchard_mapping.sim.block import simulate_block

        return simulate_block(sc, seed, out, topics=topics, progress=progress, compress=compress)

    rig = Rig.build(sc, seed)
    scene, intr, renderer, sensor = rig.scene, rig.intrinsics, rig.renderer, rig.sensor
    dh = sc.trunk.diameter_height_m
    acc = {side: VisibilityAccumulator(scene, intr, dh) for side in ("front", "back")}
    path_rng = np.random.default_rng([seed, 1])

    paths: dict[str, CameraPath] = {}
    bags: dict[str, Path] = {}
    frames: dict[str, int] = {}
    if sc.path.mode == "loop":
        loop = rig.path("front", path_rng, T0_FRONT)
        mask_dir = _mask_dir(out, "loop", sc)
        _record(scene, renderer, sensor, loop, out / "loop", mask_dir, sc.masks_every,
                np.random.default_rng([seed, 2]), acc, topics, "loop", progress, with_side_topic=True,
                compress=compress)
        bags["loop"] = out / "loop"
        frames["loop"] = len(loop.stamps)
        for side in ("front", "back"):
            m = loop.sides == side
            paths[side] = CameraPath(loop.stamps[m], loop.poses[m], loop.sides[m],
                                     float(np.sum(np.linalg.norm(np.diff(loop.poses[m, :3, 3], axis=0), axis=1))))
        # One continuous drive: both sides share the reconstruction frame of the first frame.
        T_world_odom = {side: loop.poses[0] for side in ("front", "back")}
    else:
        t0 = T0_FRONT
        for k, side in enumerate(("front", "back")):
            paths[side] = rig.path(side, path_rng, t0)
            t0 = float(paths[side].stamps[-1]) + SIDE_GAP_S
            if side not in record:
                continue
            _record(scene, renderer, sensor, paths[side], out / side, _mask_dir(out, side, sc), sc.masks_every,
                    np.random.default_rng([seed, 2 + k]), acc, topics, side, progress, with_side_topic=False,
                    compress=compress)
            bags[side] = out / side
            frames[side] = len(paths[side].stamps)
        T_world_odom = {side: paths[side].poses[0] for side in ("front", "back")}

    bag_of = {side: "loop" if sc.path.mode == "loop" else side for side in ("front", "back")}
    recorded = {side: sc.path.mode == "loop" or side in record for side in ("front", "back")}
    truth = truth_document(sc, seed, scene, acc, paths, T_world_odom, bag_of, recorded)
    write_tree_surfaces(scene, out / TREE_SURFACES_NPZ)  # before the truth file: its presence means "complete"
    truth_path = out / "ground_truth.json"
    atomic_write_text(truth_path, json.dumps(truth, indent=1))
    log.info("simulated %s: %s", out, frames)
    return SimulationResult(out, bags, truth_path, frames)


def _mask_dir(out: Path, label: str, sc: Scenario) -> Path | None:
    if not sc.masks_every:
        return None
    d = out / "masks" / label
    d.mkdir(parents=True, exist_ok=True)
    return d
