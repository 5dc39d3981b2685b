"""A side map (core.sidemap.SideMap, with its trunk landmarks, views and grounds) as bytes, and back; likewise a
side's geometry before its trunks (core.sidemap.SideGeometry, what the local_ground_fitter node reads).

The odometry node hands each finished side to the side merger as one `orchard_mapping_msgs/SideMap`
message (a recorder keeps it in the bag, so a merge can be re-run from a recording). The bytes are an
uncompressed .npz: every array of the map as its own entry (dtype and shape kept exactly) and one entry
`__tree__` holding the rest as JSON, where a frozen dataclass is {"$type": name, "fields": {...}} and an
array a reference to its entry. Decoding builds only the dataclasses listed in `_TYPES` and loads no
pickle, so bytes from the network cannot run code. A decoded map equals the encoded one exactly (floats
travel as their bits: the merge gives the same trees as offline, tests/ros).
"""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile
from typing import Any

import numpy as np

from orchard_mapping.core.cylinder import Cylinder, CylinderFit, CylinderView
from orchard_mapping.core.detection import Detection
from orchard_mapping.core.fruit import SideFruit
from orchard_mapping.core.ground import LocalGroundFit
from orchard_mapping.core.posts import PostLandmark, PostObservation
from orchard_mapping.core.sidemap import LoopClosure, Observations, SideGeometry, SideMap
from orchard_mapping.core.trunks import TrunkLandmark, TrunkObservation, TrunkView
from orchard_mapping.core.types import CameraIntrinsics, ImagePatch
from orchard_mapping.errors import OrchardMappingError

__all__ = ["SIDE_GEOMETRY_ENCODING", "SIDE_MAP_ENCODING", "SideMapFormatError", "decode_side_geometry",
           "decode_side_map", "encode_side_geometry", "encode_side_map"]

SIDE_MAP_ENCODING = "orchard_mapping.side_map/1+npz"
SIDE_GEOMETRY_ENCODING = "orchard_mapping.side_geometry/1+npz"

_TYPES = {cls.__name__: cls for cls in (SideMap, SideGeometry, CameraIntrinsics, Observations, LoopClosure,
                                        TrunkLandmark, TrunkObservation, TrunkView, Detection, Cylinder, CylinderFit,
                                        CylinderView, LocalGroundFit, ImagePatch, PostLandmark, PostObservation,
                                        SideFruit)}
_TREE = "__tree__"


class SideMapFormatError(OrchardMappingError, ValueError):
    """Bytes that are not a side map of this encoding (names where: the message, the entry, the field)."""


def encode_side_map(sm: SideMap) -> bytes:
    """The side map as the bytes of SIDE_MAP_ENCODING."""
    return _encode(sm, "side_map")


def encode_side_geometry(geometry: SideGeometry) -> bytes:
    """The side's geometry as the bytes of SIDE_GEOMETRY_ENCODING."""
    return _encode(geometry, "side_geometry")


def decode_side_map(data: bytes, where: str = "side map") -> SideMap:
    """The SideMap of `data` (encode_side_map's bytes); SideMapFormatError naming `where` and the field."""
    return _decode(data, where, SideMap, SIDE_MAP_ENCODING)


def decode_side_geometry(data: bytes, where: str = "side geometry") -> SideGeometry:
    """The SideGeometry of `data` (encode_side_geometry's bytes); SideMapFormatError naming `where` and the field."""
    return _decode(data, where, SideGeometry, SIDE_GEOMETRY_ENCODING)


def _encode(obj: Any, root: str) -> bytes:
    arrays: dict[str, np.ndarray] = {}

    def enc(v: Any, where: str) -> Any:
        if isinstance(v, np.ndarray):
            key = f"a{len(arrays)}"
            if v.dtype == object:
                raise SideMapFormatError(f"{where}: an object array cannot be encoded")
            arrays[key] = v
            return {"$array": key}
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            name = type(v).__name__
            if _TYPES.get(name) is not type(v):
                raise SideMapFormatError(f"{where}: {name} is not a side map type")
            return {"$type": name, "fields": {f.name: enc(getattr(v, f.name), f"{where}.{f.name}")
                                              for f in dataclasses.fields(v)}}
        if isinstance(v, (list, tuple)):
            return {"$list" if isinstance(v, list) else "$tuple": [enc(x, f"{where}[{i}]") for i, x in enumerate(v)]}
        if isinstance(v, np.generic):
            return v.item()
        if v is None or isinstance(v, (bool, int, float, str)):
            return v
        raise SideMapFormatError(f"{where}: a {type(v).__name__} cannot be encoded")

    tree = enc(obj, root)
    buf = io.BytesIO()
    # allow_nan: NaN marks an unmeasured value (e.g. a ground's support offset); Python's json reads it back
    np.savez(buf, **{_TREE: np.frombuffer(json.dumps(tree, allow_nan=True).encode(), np.uint8)}, **arrays)
    return buf.getvalue()


def _decode(data: bytes, where: str, want: type, encoding: str) -> Any:
    try:
        with np.load(io.BytesIO(bytes(data)), allow_pickle=False) as z:
            entries = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise SideMapFormatError(f"{where}: not a {encoding} payload: {err}") from err
    if _TREE not in entries:
        raise SideMapFormatError(f"{where}: no {_TREE} entry: not a {encoding} payload")
    try:
        tree = json.loads(entries.pop(_TREE).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise SideMapFormatError(f"{where}: {_TREE} is not JSON: {err}") from err

    def dec(v: Any, at: str) -> Any:
        if isinstance(v, dict):
            if "$array" in v:
                if v["$array"] not in entries:
                    raise SideMapFormatError(f"{where}: {at} refers to a missing array entry {v['$array']!r}")
                return entries[v["$array"]]
            if "$list" in v:
                return [dec(x, f"{at}[{i}]") for i, x in enumerate(v["$list"])]
            if "$tuple" in v:
                return tuple(dec(x, f"{at}[{i}]") for i, x in enumerate(v["$tuple"]))
            cls = _TYPES.get(v.get("$type", ""))
            if cls is None or not isinstance(v.get("fields"), dict):
                raise SideMapFormatError(f"{where}: {at} is not a side map type ({v.get('$type')!r})")
            names = {f.name for f in dataclasses.fields(cls)}
            # a field added since the bytes were written (it has a default) may be missing; nothing else
            defaulted = {f.name for f in dataclasses.fields(cls)
                         if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING}
            if not (set(v["fields"]) <= names and names - set(v["fields"]) <= defaulted):
                raise SideMapFormatError(f"{where}: {at} ({cls.__name__}) has fields {sorted(v['fields'])}, "
                                         f"expected {sorted(names)}")
            return cls(**{k: dec(x, f"{at}.{k}") for k, x in v["fields"].items()})
        if isinstance(v, list):
            raise SideMapFormatError(f"{where}: {at} is a bare list")
        return v

    out = dec(tree, "side_map" if want is SideMap else "side_geometry")
    if not isinstance(out, want):
        raise SideMapFormatError(f"{where}: the payload is a {type(out).__name__}, not a {want.__name__}")
    return out
