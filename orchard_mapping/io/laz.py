"""trees.laz: the merged cloud, each point classified and given its tree, as ASPRS LAS 1.4 (LAZ-compressed).

Point format 7 (x y z, RGB), ASPRS classes where one fits (1 unclassified, 2 ground, 5 high vegetation for
the canopy, 14 wire for the trellis wires) and the project's own codes in the user range (64-255) for what ASPRS has no class for: trunk,
post, fruit (CLASS below; docs/results.md). Two extra dimensions: `tree_id` (int32, -1: no tree) and `side`
(uint8, 0 front, 1 back: the side whose camera saw the point). Coordinates are the map frame of
trees.json (m; the front side's odom frame): a local frame with no CRS, named in the header's system
identifier, at 0.1 mm resolution. The header's creation day is the recording's (UTC), not the day the file was
written, so the same recording gives the same bytes. CloudCompare, PDAL and lidR open it as any LAZ file.
"""

from __future__ import annotations

import os
import tempfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from orchard_mapping.errors import OrchardMappingError

__all__ = ["CLASS", "LAZ_SCALE_M", "SIDE_CODE", "read_laz", "write_laz"]

# per-point class codes: ASPRS LAS 1.4 where it has one, the user range (64-255) for the orchard's own
TREES_LAZ = "trees.laz"  # its name in a result folder
CLASS = {"none": 1, "ground": 2, "canopy": 5, "wire": 14, "trunk": 64, "post": 65, "fruit": 66}
SIDE_CODE = {"front": 0, "back": 1}
LAZ_SCALE_M = 1e-4  # m per coordinate unit: 0.1 mm, far below the depth noise (mm at 1 m)
SYSTEM_ID = "orchard_mapping map (local)"  # 32 bytes at most: the header's system identifier


class LazWriteError(OrchardMappingError):
    """The arrays given for trees.laz do not agree (which one, and how)."""


def write_laz(path: str | Path, points: np.ndarray, colors: np.ndarray, classification: np.ndarray,
              tree_id: np.ndarray, side: np.ndarray, recorded_s: float = 0.0) -> Path:
    """Write trees.laz atomically (a temporary file renamed into place).

    points (N, 3) float m, map frame; colors (N, 3) uint8 RGB; classification (N,) uint8 (CLASS values);
    tree_id (N,) int (-1: none); side (N,) uint8 (SIDE_CODE values); recorded_s: a stamp of the recording,
    s since the epoch (its UTC day is the header's creation day)."""
    import laspy

    path = Path(path)
    pts = np.asarray(points, dtype=np.float64)
    n = len(pts)
    arrays = {"points": (pts, (n, 3)), "colors": (np.asarray(colors), (n, 3)),
              "classification": (np.asarray(classification), (n,)), "tree_id": (np.asarray(tree_id), (n,)),
              "side": (np.asarray(side), (n,))}
    for name, (a, shape) in arrays.items():
        if a.shape != shape:
            raise LazWriteError(f"{path}: {name} has shape {a.shape}, expected {shape} (N = {n} points)")
    if n and not np.isfinite(pts).all():
        raise LazWriteError(f"{path}: points hold {int(np.sum(~np.isfinite(pts).all(axis=1)))} non-finite rows")
    header = laspy.LasHeader(point_format=7, version="1.4")
    header.system_identifier = SYSTEM_ID
    header.generating_software = "orchard_mapping"
    # laspy would write today's date: the recording's day keeps the file the same on every run of it
    header.creation_date = datetime.fromtimestamp(float(recorded_s), timezone.utc).date()
    header.scales = np.full(3, LAZ_SCALE_M)
    header.offsets = np.floor(pts.min(axis=0)) if n else np.zeros(3)
    header.add_extra_dims([laspy.ExtraBytesParams(name="tree_id", type=np.int32, description="tree of trees.json"),
                           laspy.ExtraBytesParams(name="side", type=np.uint8, description="0 front, 1 back")])
    las = laspy.LasData(header)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    rgb = np.asarray(colors, dtype=np.uint16) * 257  # 8 -> 16 bit, 255 -> 65535
    las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.classification = np.asarray(classification, dtype=np.uint8)
    las.tree_id = np.asarray(tree_id, dtype=np.int32)
    las.side = np.asarray(side, dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=".laz", dir=path.parent)
    os.close(fd)
    try:
        las.write(tmp, laz_backend=laspy.LazBackend.Lazrs)
        os.chmod(tmp, 0o644)  # as the result folder's other files (mkstemp makes it 0600)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_laz(path: str | Path) -> dict[str, np.ndarray]:
    """What write_laz wrote: points (N, 3) m, colors (N, 3) uint8, classification, tree_id, side."""
    import laspy

    las = laspy.read(str(path), laz_backend=laspy.LazBackend.Lazrs)
    return {"points": np.column_stack([las.x, las.y, las.z]).astype(float),
            "colors": (np.column_stack([las.red, las.green, las.blue]) // 257).astype(np.uint8),
            "classification": np.asarray(las.classification, dtype=np.uint8),
            "tree_id": np.asarray(las.tree_id, dtype=np.int32), "side": np.asarray(las.side, dtype=np.uint8)}
