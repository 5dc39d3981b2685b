"""Loader of ground_truth.json (schema `orchard_mapping.ground_truth/1`, docs/ground_truth.md).

Validates the fields the evaluator relies on and raises `GroundTruthError`
naming the file and the dotted field (e.g. `trees[2].trunk.diameter_m`).
Positions stay in the frames the file states (world for trees and fruit,
odom_<side> for trajectories).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.errors import GroundTruthError
from orchard_mapping.io.results import load_json

__all__ = [
    "GROUND_TRUTH_SCHEMA",
    "SIDES",
    "GroundTruth",
    "TrueSide",
    "TrueTree",
    "load_ground_truth",
    "parse_ground_truth",
]

GROUND_TRUTH_SCHEMA = "orchard_mapping.ground_truth/1"
SIDES = ("front", "back")


@dataclass(frozen=True)
class TrueTree:
    """One simulated tree (world frame)."""

    id: int
    position: np.ndarray  # (3,) m, world: trunk axis at local ground
    trunk_base: np.ndarray  # (3,) m, world
    trunk_top: np.ndarray  # (3,) m, world
    diameter_m: float  # m, at diameter_height_m above local ground
    height_m: float  # m above the local ground plane
    canopy_volume_m3: float  # m^3
    fruit_ids: np.ndarray  # (F,) int
    fruit_positions: np.ndarray  # (F, 3) m, world
    fruit_radii: np.ndarray  # (F,) m
    fruit_count: int
    fruit_visible: Mapping[str, int]  # front, back, either, both
    trunk_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # (3,) unit, world
    ground_point: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) m, world: local ground plane
    ground_normal: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))  # (3,) unit, up
    # side -> trunk seen at the diameter height from that side (None: the file does not say)
    trunk_seen: Mapping[str, bool | None] = field(default_factory=dict)
    # side -> (point (3,), normal (3,)) of the local ground that side saw (None: not stated / not seen enough)
    seen_ground: Mapping[str, tuple[np.ndarray, np.ndarray] | None] = field(default_factory=dict)


@dataclass(frozen=True)
class TrueSide:
    """One side's recording: its odom frame in world and the true camera trajectory."""

    name: str  # "front" / "back"
    frame: str  # "odom_<side>"
    T_world_odom: np.ndarray  # (4, 4)
    path_length_m: float  # m
    duration_s: float  # s
    trajectory: StampedTrajectory  # camera optical frame in odom_<side>, every frame


@dataclass(frozen=True)
class GroundTruth:
    path: Path
    trees: tuple[TrueTree, ...]
    sides: Mapping[str, TrueSide]
    T_front_back: np.ndarray  # (4, 4): odom_back -> odom_front
    diameter_height_m: float | None = None  # m
    canopy_alpha_m: float | None = None  # m
    raw: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)


class _Check:
    """Field access that names the file and the dotted field on failure."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def fail(self, where: str, msg: str) -> GroundTruthError:
        return GroundTruthError(f"{self.path}: field '{where}': {msg}")

    def obj(self, v: Any, where: str) -> Mapping[str, Any]:
        if not isinstance(v, Mapping):
            raise self.fail(where or "<root>", f"expected an object, got {type(v).__name__}")
        return v

    def get(self, d: Mapping[str, Any], key: str, where: str) -> Any:
        dotted = f"{where}.{key}" if where else key
        if key not in d:
            raise self.fail(dotted, "missing")
        return d[key]

    def num(self, v: Any, where: str, minimum: float | None = None) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise self.fail(where, f"expected a finite number, got {v!r}")
        if minimum is not None and v < minimum:
            raise self.fail(where, f"must be >= {minimum}, got {v!r}")
        return float(v)

    def integer(self, v: Any, where: str) -> int:
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(where, f"expected an integer, got {v!r}")
        return v

    def arr(self, v: Any, shape: tuple[int, ...], where: str) -> np.ndarray:
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError) as err:
            raise self.fail(where, f"expected numbers of shape {shape}: {err}") from err
        if a.size == 0 and -1 in shape:
            a = a.reshape(tuple(0 if s == -1 else s for s in shape))
        if a.ndim != len(shape) or any(s != -1 and s != n for s, n in zip(shape, a.shape, strict=True)):
            raise self.fail(where, f"expected shape {shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise self.fail(where, "contains a non-finite value")
        return a

    def transform(self, v: Any, where: str) -> np.ndarray:
        T = self.arr(v, (4, 4), where)
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise self.fail(where, f"last row must be [0, 0, 0, 1], got {T[3].tolist()}")
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            raise self.fail(where, "3x3 block is not a rotation")
        return T


def _tree(c: _Check, t: Any, w: str) -> TrueTree:
    t = c.obj(t, w)
    trunk = c.obj(c.get(t, "trunk", w), f"{w}.trunk")
    ground = c.obj(c.get(t, "local_ground", w), f"{w}.local_ground")
    g_point = c.arr(c.get(ground, "point", f"{w}.local_ground"), (3,), f"{w}.local_ground.point")
    g_normal = c.arr(c.get(ground, "normal", f"{w}.local_ground"), (3,), f"{w}.local_ground.normal")
    axis = c.arr(c.get(trunk, "axis", f"{w}.trunk"), (3,), f"{w}.trunk.axis")
    trunk_seen: dict[str, bool | None] = {}
    seen_ground: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}
    observed = t.get("observed")
    for side in SIDES:
        ob = c.obj(observed.get(side, {}), f"{w}.observed.{side}") if isinstance(observed, Mapping) else {}
        v = ob.get("trunk_at_diameter_height")
        trunk_seen[side] = bool(v) if isinstance(v, bool) else None
        lg = ob.get("local_ground")
        if lg is None:
            seen_ground[side] = None
        else:
            ow = f"{w}.observed.{side}.local_ground"
            lg = c.obj(lg, ow)
            seen_ground[side] = (c.arr(c.get(lg, "point", ow), (3,), f"{ow}.point"),
                                 c.arr(c.get(lg, "normal", ow), (3,), f"{ow}.normal"))
    fruit = c.get(t, "fruit", w)
    if not isinstance(fruit, list):
        raise c.fail(f"{w}.fruit", f"expected a list, got {type(fruit).__name__}")
    ids, pos, radii = [], [], []
    for j, f in enumerate(fruit):
        fw = f"{w}.fruit[{j}]"
        f = c.obj(f, fw)
        ids.append(c.integer(c.get(f, "id", fw), f"{fw}.id"))
        pos.append(c.arr(c.get(f, "position", fw), (3,), f"{fw}.position"))
        radii.append(c.num(c.get(f, "radius_m", fw), f"{fw}.radius_m", minimum=0.0))
        vis = c.obj(c.get(f, "visible", fw), f"{fw}.visible")
        for side in SIDES:
            if not isinstance(c.get(vis, side, f"{fw}.visible"), bool):
                raise c.fail(f"{fw}.visible.{side}", f"expected true/false, got {vis[side]!r}")
    fv = c.obj(c.get(t, "fruit_visible", w), f"{w}.fruit_visible")
    visible = {
        k: c.integer(c.get(fv, k, f"{w}.fruit_visible"), f"{w}.fruit_visible.{k}")
        for k in ("front", "back", "either", "both")
    }
    fruit_count = c.integer(c.get(t, "fruit_count", w), f"{w}.fruit_count")
    return TrueTree(
        id=c.integer(c.get(t, "id", w), f"{w}.id"),
        position=c.arr(c.get(t, "position", w), (3,), f"{w}.position"),
        trunk_base=c.arr(c.get(trunk, "base", f"{w}.trunk"), (3,), f"{w}.trunk.base"),
        trunk_top=c.arr(c.get(trunk, "top", f"{w}.trunk"), (3,), f"{w}.trunk.top"),
        diameter_m=c.num(c.get(trunk, "diameter_m", f"{w}.trunk"), f"{w}.trunk.diameter_m", minimum=0.0),
        height_m=c.num(c.get(t, "height_m", w), f"{w}.height_m", minimum=0.0),
        canopy_volume_m3=c.num(c.get(t, "canopy_volume_m3", w), f"{w}.canopy_volume_m3", minimum=0.0),
        fruit_ids=np.asarray(ids, dtype=int),
        fruit_positions=np.asarray(pos, dtype=float).reshape(-1, 3),
        fruit_radii=np.asarray(radii, dtype=float),
        fruit_count=fruit_count,
        fruit_visible=visible,
        trunk_axis=axis / max(np.linalg.norm(axis), 1e-12),
        ground_point=g_point,
        ground_normal=g_normal / max(np.linalg.norm(g_normal), 1e-12),
        trunk_seen=trunk_seen,
        seen_ground=seen_ground,
    )


def _side(c: _Check, name: str, s: Any, w: str) -> TrueSide:
    s = c.obj(s, w)
    traj = c.arr(c.get(s, "trajectory", w), (-1, 8), f"{w}.trajectory")  # (N, 8)
    if traj.shape[0] == 0:
        raise c.fail(f"{w}.trajectory", "no poses")
    if np.any(np.diff(traj[:, 0]) <= 0.0):
        raise c.fail(f"{w}.trajectory", "stamps are not strictly increasing")
    qn = np.linalg.norm(traj[:, 4:8], axis=1, keepdims=True)
    if np.any(qn < 1e-12):
        raise c.fail(f"{w}.trajectory", "zero quaternion")
    frame = c.get(s, "frame", w)
    if not isinstance(frame, str):
        raise c.fail(f"{w}.frame", f"expected a string, got {frame!r}")
    return TrueSide(
        name=name,
        frame=frame,
        T_world_odom=c.transform(c.get(s, "T_world_odom", w), f"{w}.T_world_odom"),
        path_length_m=c.num(c.get(s, "path_length_m", w), f"{w}.path_length_m", minimum=0.0),
        duration_s=c.num(c.get(s, "duration_s", w), f"{w}.duration_s", minimum=0.0),
        trajectory=StampedTrajectory(
            stamps=traj[:, 0].copy(), positions=traj[:, 1:4].copy(), quaternions=traj[:, 4:8] / qn, frame_id=frame
        ),
    )


def parse_ground_truth(doc: Any, path: str | Path = "<ground truth>") -> GroundTruth:
    """Validate a ground-truth document already parsed from JSON."""
    c = _Check(Path(path))
    d = c.obj(doc, "")
    schema = c.get(d, "schema", "")
    if schema != GROUND_TRUTH_SCHEMA:
        raise c.fail("schema", f"expected {GROUND_TRUTH_SCHEMA!r}, got {schema!r}")
    trees_raw = c.get(d, "trees", "")
    if not isinstance(trees_raw, list):
        raise c.fail("trees", f"expected a list, got {type(trees_raw).__name__}")
    trees = tuple(_tree(c, t, f"trees[{i}]") for i, t in enumerate(trees_raw))
    ids = [t.id for t in trees]
    if len(set(ids)) != len(ids):
        raise c.fail("trees[].id", f"ids are not unique: {sorted(ids)}")
    if "n_trees" in d and c.integer(d["n_trees"], "n_trees") != len(trees):
        raise c.fail("n_trees", f"says {d['n_trees']} but 'trees' holds {len(trees)}")
    sides_raw = c.obj(c.get(d, "sides", ""), "sides")
    sides = {name: _side(c, name, c.get(sides_raw, name, "sides"), f"sides.{name}") for name in SIDES}
    dh = d.get("diameter_height_m")
    alpha = d.get("canopy_alpha_m")
    return GroundTruth(
        path=c.path,
        trees=trees,
        sides=sides,
        T_front_back=c.transform(c.get(d, "T_front_back", ""), "T_front_back"),
        diameter_height_m=None if dh is None else c.num(dh, "diameter_height_m", minimum=0.0),
        canopy_alpha_m=None if alpha is None else c.num(alpha, "canopy_alpha_m", minimum=0.0),
        raw=d,
    )


def load_ground_truth(path: str | Path) -> GroundTruth:
    """Read and validate ground_truth.json."""
    path = Path(path)
    doc = load_json(path, GroundTruthError, "ground-truth file")
    return parse_ground_truth(doc, path)
