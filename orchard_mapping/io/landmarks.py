"""trunks.json and grounds.json: each side's trunk landmarks and local grounds (schema: docs/results.md).

Written atomically; read back with validation (`ResultFormatError` naming the
file and the dotted field). Frames: each side's entries are in that side's
reconstruction frame (`odom_<side>`), metres.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from orchard_mapping.core.cylinder import Cylinder
from orchard_mapping.core.detection import CLASS_NAMES
from orchard_mapping.core.trunks import TrunkLandmark
from orchard_mapping.io.json_fields import as_array, as_integer, as_mapping, as_number, field_error, get_field
from orchard_mapping.io.results import atomic_write_json, load_json

__all__ = [
    "GROUNDS_JSON",
    "GROUNDS_SCHEMA",
    "TRUNKS_JSON",
    "TRUNKS_SCHEMA",
    "ResultGround",
    "ResultTrunk",
    "read_grounds",
    "read_trunks",
    "write_grounds",
    "write_trunks",
]

TRUNKS_JSON, GROUNDS_JSON = "trunks.json", "grounds.json"
TRUNKS_SCHEMA, GROUNDS_SCHEMA = "orchard_mapping.trunks/1", "orchard_mapping.grounds/1"


def _vec(v: np.ndarray, nd: int = 6) -> list[float]:
    return [round(float(x), nd) for x in np.asarray(v, float).ravel()]


def _num(v: float | None, nd: int = 6) -> float | None:
    return None if v is None or not np.isfinite(v) else round(float(v), nd)


def _cyl(c: Cylinder | None) -> dict[str, Any] | None:
    return None if c is None else {"axis": _vec(c.axis), "origin": _vec(c.origin), "radius_m": _num(c.radius)}


def trunk_to_json(lm: TrunkLandmark) -> dict[str, Any]:
    band = lm.band
    return {
        "id": lm.id,
        "base": _vec(lm.base), "axis": _vec(lm.axis),
        "axis_cone": None if lm.merge_axis is None else _vec(lm.merge_axis), "taper": _num(lm.taper, 5),
        "length_m": _num(lm.length_m, 4),
        "diameter_m": _num(lm.diameter_m),
        "diameter_3d_only_m": _num(2 * lm.baseline_band.cylinder.radius) if lm.baseline_band is not None else None,
        "band": None if band is None else {
            **(_cyl(band.cylinder) or {}), "rmse_3d_m": _num(band.rmse_3d_m), "rmse_2d_px": _num(band.rmse_2d_px, 3),
            "inliers_3d": band.inliers_3d, "residuals_2d": band.n_2d},
        "n_points": lm.n_points,
        "n_observations": len(lm.observations),
        "flags": list(lm.flags),
        "observations": [{
            "keyframe": o.keyframe, "stamp": round(o.stamp, 6), "class": CLASS_NAMES.get(o.detection.class_id, "?"),
            "score": _num(o.detection.score, 4), "box": _vec(o.detection.box, 1),
            "mask_pixels": int(o.detection.mask.sum()), "band_pixels": o.band_pixels,
            "cylinder_cam": _cyl(o.cylinder_cam)} for o in lm.observations],
    }


def write_trunks(path: str | Path, sides: Mapping[str, tuple[str, list[TrunkLandmark]]],
                 diameter_height_m: float) -> Path:
    """sides: side -> (frame id, landmarks)."""
    doc = {"schema": TRUNKS_SCHEMA, "diameter_height_m": diameter_height_m,
           "sides": {s: {"frame": frame, "trunks": [trunk_to_json(lm) for lm in lms]}
                     for s, (frame, lms) in sides.items()}}
    return atomic_write_json(path, doc)


def write_grounds(path: str | Path, sides: Mapping[str, tuple[str, list[TrunkLandmark]]]) -> Path:
    doc: dict[str, Any] = {"schema": GROUNDS_SCHEMA, "sides": {}}
    for s, (frame, lms) in sides.items():
        grounds = [{"trunk_id": lm.id, "normal": _vec(lm.ground.normal), "offset_m": _num(lm.ground.offset),
                    "point": _vec(lm.ground.point), "inliers": lm.ground.inliers, "rmse_m": _num(lm.ground.rmse_m),
                    "candidates": lm.ground.candidates, "support_m2": _num(lm.ground.support_m2),
                    "support_offset_m": _num(lm.ground.support_offset_m)}
                   for lm in lms if lm.ground is not None]
        doc["sides"][s] = {"frame": frame, "grounds": grounds}
    return atomic_write_json(path, doc)


@dataclass(frozen=True)
class ResultTrunk:
    side: str
    id: int
    base: np.ndarray  # (3,) m, odom_<side>
    axis: np.ndarray  # (3,) unit
    diameter_m: float | None
    diameter_3d_only_m: float | None
    length_m: float
    stamps: np.ndarray  # (O,) s, the observations' stamps
    flags: tuple[str, ...]
    axis_cone: np.ndarray | None = None  # (3,) unit, the whole trunk's axis with its taper modelled


@dataclass(frozen=True)
class ResultGround:
    side: str
    trunk_id: int
    normal: np.ndarray  # (3,) unit, up
    point: np.ndarray  # (3,) m, where the trunk axis meets the plane


def _doc(path: Path, schema: str) -> Mapping[str, Any]:
    doc = as_mapping(load_json(path), path, "")
    if doc.get("schema") != schema:
        raise field_error(path, "schema", f"expected {schema!r}, got {doc.get('schema')!r}")
    return as_mapping(get_field(doc, "sides", path, ""), path, "sides")


def _entries(path: Path, schema: str, key: str) -> Iterator[tuple[str, str, Mapping[str, Any]]]:
    """(side, dotted field name, entry) of every entry in sides.<side>.<key> of a landmarks file."""
    for side, body in _doc(path, schema).items():
        items = get_field(as_mapping(body, path, f"sides.{side}"), key, path, f"sides.{side}")
        if not isinstance(items, list):
            raise field_error(path, f"sides.{side}.{key}", "expected a list")
        for i, item in enumerate(items):
            w = f"sides.{side}.{key}[{i}]"
            yield side, w, as_mapping(item, path, w)


def read_trunks(path: str | Path) -> list[ResultTrunk]:
    path = Path(path)
    out = []
    for side, w, t in _entries(path, TRUNKS_SCHEMA, "trunks"):
        obs = get_field(t, "observations", path, w)
        if not isinstance(obs, list):
            raise field_error(path, f"{w}.observations", "expected a list")
        out.append(ResultTrunk(
            side=side, id=int(as_integer(get_field(t, "id", path, w), path, f"{w}.id")),
            base=as_array(get_field(t, "base", path, w), (3,), path, f"{w}.base"),
            axis=as_array(get_field(t, "axis", path, w), (3,), path, f"{w}.axis"),
            diameter_m=as_number(get_field(t, "diameter_m", path, w), path, f"{w}.diameter_m", nullable=True, minimum=0),
            diameter_3d_only_m=as_number(t.get("diameter_3d_only_m"), path, f"{w}.diameter_3d_only_m",
                                       nullable=True, minimum=0),
            length_m=float(as_number(get_field(t, "length_m", path, w), path, f"{w}.length_m") or 0.0),
            stamps=np.array([as_number(get_field(as_mapping(o, path, f"{w}.observations[{k}]"), "stamp", path,
                                          f"{w}.observations[{k}]"), path, f"{w}.observations[{k}].stamp")
                             for k, o in enumerate(obs)], float),
            flags=tuple(str(f) for f in t.get("flags", [])),
            axis_cone=None if t.get("axis_cone") is None else as_array(t["axis_cone"], (3,), path, f"{w}.axis_cone")))
    return out


def read_grounds(path: str | Path) -> list[ResultGround]:
    path = Path(path)
    out = []
    for side, w, g in _entries(path, GROUNDS_SCHEMA, "grounds"):
        n = as_array(get_field(g, "normal", path, w), (3,), path, f"{w}.normal")
        if abs(np.linalg.norm(n) - 1.0) > 1e-3:
            raise field_error(path, f"{w}.normal", f"expected a unit vector, got norm {np.linalg.norm(n):.4f}")
        out.append(ResultGround(side, int(as_integer(get_field(g, "trunk_id", path, w), path, f"{w}.trunk_id")), n,
                                as_array(get_field(g, "point", path, w), (3,), path, f"{w}.point")))
    return out
