"""A small synthetic ground truth (docs/ground_truth.md) and a result folder derived from it exactly."""

from __future__ import annotations

import json
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.io.results import write_side_merge, write_timings, write_trees, write_tum

RATE_HZ = 15.0
N_POSES = 31  # 2 s per side
KEYFRAME_STEP = 3


def _T(R: np.ndarray, t: Any) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _side(T_world_odom: np.ndarray, t0: float) -> dict[str, Any]:
    """A camera sweeping ~2 m along its own x with a little wiggle and yaw (optical frame)."""
    s = np.linspace(0.0, 2.0, N_POSES)
    pos = np.column_stack([s, 0.05 * np.sin(2.0 * s), 0.02 * s])  # (N, 3) odom
    rot = Rotation.from_euler("y", 4.0 * np.sin(1.5 * s)[:, None], degrees=True)  # yaw about optical y (down)
    stamps = t0 + np.arange(N_POSES) / RATE_HZ
    traj = np.column_stack([stamps, pos, rot.as_quat()])
    return {
        "frame": "",
        "bag": "",
        "T_world_odom": T_world_odom.tolist(),
        "path_length_m": float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum()),
        "duration_s": float(stamps[-1] - stamps[0]),
        "trajectory": traj.tolist(),
    }


def make_truth() -> dict[str, Any]:
    x_w, y_w, z_w = np.eye(3)
    # Front camera right of the row looking +y_w, back camera left of it looking -y_w
    # (optical frame: x right, y down, z forward).
    T_w_front = _T(np.column_stack([x_w, -z_w, y_w]), [-0.5, -1.2, 0.9])
    T_w_back = _T(np.column_stack([-x_w, -z_w, -y_w]), [5.5, 1.3, 0.95])
    trees = []
    fruit_offsets = np.array(
        [[0.3, 0.2, 1.4], [-0.3, -0.2, 1.6], [0.0, 0.35, 1.9], [0.1, -0.35, 1.2], [-0.2, 0.1, 2.1]]
    )
    for i, x in enumerate([0.0, 2.5, 5.0]):
        base = np.array([x, 0.03 * i, 0.05 * i])
        fruit = []
        for j, off in enumerate(fruit_offsets[: 3 + i]):
            vis = {"front": bool(off[1] <= 0.1), "back": bool(off[1] >= -0.1)}
            if j == 2:
                vis = {"front": False, "back": False}  # hidden inside the canopy
            fruit.append({"id": j, "position": (base + off).tolist(), "radius_m": 0.04, "color": "red", "visible": vis})
        fv = {
            "front": sum(f["visible"]["front"] for f in fruit),
            "back": sum(f["visible"]["back"] for f in fruit),
            "either": sum(f["visible"]["front"] or f["visible"]["back"] for f in fruit),
            "both": sum(f["visible"]["front"] and f["visible"]["back"] for f in fruit),
        }
        trees.append(
            {
                "id": i,
                "position": base.tolist(),
                "trunk": {
                    "base": base.tolist(),
                    "top": (base + [0, 0, 0.62]).tolist(),
                    "axis": [0.0, 0.0, 1.0],
                    "diameter_m": 0.060 + 0.005 * i,
                    "base_diameter_m": 0.072,
                    "top_diameter_m": 0.058,
                    "clear_height_m": 0.62,
                },
                "local_ground": {"point": base.tolist(), "normal": [0.0, 0.0, 1.0]},
                "height_m": 2.1 + 0.2 * i,
                "canopy_volume_m3": 1.0 + 0.25 * i,
                "fruit": fruit,
                "fruit_count": len(fruit),
                "fruit_visible": fv,
                "observed": {
                    "front": {"trunk_at_diameter_height": True, "top": True, "canopy_fraction": 0.4},
                    "back": {"trunk_at_diameter_height": True, "top": True, "canopy_fraction": 0.45},
                },
            }
        )
    front = _side(T_w_front, 100.0)
    back = _side(T_w_back, 200.0)
    front.update(frame="odom_front", bag="front")
    back.update(frame="odom_back", bag="back")
    return {
        "schema": "orchard_mapping.ground_truth/1",
        "scenario": "unit",
        "seed": 0,
        "n_trees": 3,
        "diameter_height_m": 0.30,
        "canopy_alpha_m": 0.8,
        "canopy_volume_definition": "alpha shape",
        "height_definition": "highest point above local ground",
        "camera": {
            "width": 640,
            "height": 480,
            "fx": 615.0,
            "fy": 615.0,
            "cx": 319.5,
            "cy": 239.5,
            "rate_hz": RATE_HZ,
            "depth_sigma_coeff": 0.004,
        },
        "trees": trees,
        "posts": [{"position": [-1.0, 0.0, 0.0], "diameter_m": 0.1, "height_m": 2.8}],
        "sides": {"front": front, "back": back},
        "T_front_back": (np.linalg.inv(T_w_front) @ T_w_back).tolist(),
    }


def to_front(truth: dict[str, Any], pts_world: Any) -> np.ndarray:
    """World points (N, 3) -> odom_front."""
    T = np.linalg.inv(np.asarray(truth["sides"]["front"]["T_world_odom"]))
    p = np.asarray(pts_world, dtype=float).reshape(-1, 3)
    return p @ T[:3, :3].T + T[:3, 3]


def true_trajectory(truth: dict[str, Any], side: str, step: int = 1) -> StampedTrajectory:
    a = np.asarray(truth["sides"][side]["trajectory"])[::step]
    return StampedTrajectory(stamps=a[:, 0], positions=a[:, 1:4], quaternions=a[:, 4:8], frame_id=f"odom_{side}")


def exact_trees(truth: dict[str, Any]) -> list[dict[str, Any]]:
    """Result trees equal to the truth: fruit = the fruit visible from either side."""
    out = []
    for t in truth["trees"]:
        vis = [f["position"] for f in t["fruit"] if f["visible"]["front"] or f["visible"]["back"]]
        out.append(
            {
                "id": 10 + t["id"],
                "position": to_front(truth, t["position"])[0],
                "trunk_diameter_m": t["trunk"]["diameter_m"],
                "height_m": t["height_m"],
                "canopy_volume_m3": t["canopy_volume_m3"],
                "fruit_count": len(vis),
                "fruit_positions": to_front(truth, vis),
                "flags": [],
            }
        )
    return out


def write_exact_result(truth: dict[str, Any], result_dir: Path) -> Path:
    result_dir.mkdir(parents=True, exist_ok=True)
    write_trees(result_dir, exact_trees(truth))
    write_side_merge(result_dir / "side_merge.json", np.asarray(truth["T_front_back"]), residuals={"trunks_m": 0.0})
    T_map_odom = {"front": np.eye(4), "back": np.asarray(truth["T_front_back"])}
    for side in ("front", "back"):
        kf = true_trajectory(truth, side, KEYFRAME_STEP)
        write_tum(result_dir / f"trajectory_{side}.tum", kf)
        T = T_map_odom[side]
        R = T[:3, :3] @ Rotation.from_quat(kf.quaternions).as_matrix()  # (K, 3, 3)
        write_tum(result_dir / f"trajectory_{side}_map.tum",
                  StampedTrajectory(kf.stamps, kf.positions @ T[:3, :3].T + T[:3, 3], Rotation.from_matrix(R).as_quat()))
    write_timings(
        result_dir / "timings.json", {"odometry": 2.0, "merge": 0.5, "traits": 1.5}, frames=62, recording_duration_s=4.0
    )
    return result_dir


@pytest.fixture()
def truth() -> dict[str, Any]:
    return make_truth()


@pytest.fixture()
def truth_path(tmp_path: Path, truth: dict[str, Any]) -> Path:
    path = tmp_path / "ground_truth.json"
    path.write_text(json.dumps(truth, indent=1))
    return path


@pytest.fixture()
def result_dir(tmp_path: Path, truth: dict[str, Any]) -> Path:
    return write_exact_result(truth, tmp_path / "result")


@pytest.fixture()
def kit() -> types.SimpleNamespace:
    """The helpers above, for tests (conftest is not imported by name)."""
    return types.SimpleNamespace(
        make_truth=make_truth,
        to_front=to_front,
        true_trajectory=true_trajectory,
        exact_trees=exact_trees,
        write_exact_result=write_exact_result,
        keyframe_step=KEYFRAME_STEP,
    )
