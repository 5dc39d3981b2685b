"""Writers and readers of the result folder (contract: docs/results.md).

Every writer is atomic: the text is serialised first, written to a temporary
file in the target's folder, fsynced and renamed over the target, so a reader
never sees a partial file and a failed write leaves the previous content.
Readers validate and raise `ResultFormatError` naming the file and the field
(or line).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import errno
import io
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from orchard_mapping.core.types import StampedTrajectory
from orchard_mapping.errors import OutputError, ResultFormatError
from orchard_mapping.io.json_fields import as_array, as_integer, as_mapping, as_number, field_error, get_field

__all__ = [
    "RESULT_SCHEMA",
    "SIDE_MERGE_JSON",
    "TIMINGS_JSON",
    "TREES_CSV",
    "TREES_CSV_COLUMNS",
    "TREES_FRAMES",
    "TREES_JSON",
    "ResultTree",
    "SideMerge",
    "Timings",
    "atomic_write_json",
    "atomic_write_text",
    "portable_json",
    "staged_folder",
    "load_json",
    "read_side_merge",
    "read_timings",
    "read_trees",
    "read_trees_csv",
    "read_tum",
    "to_jsonable",
    "trajectory_filename",
    "map_trajectory_filename",
    "write_side_merge",
    "write_timings",
    "write_trees",
    "write_tum",
]

RESULT_SCHEMA = "orchard_mapping.result/1"
TREES_JSON = "trees.json"
TREES_CSV = "trees.csv"
SIDE_MERGE_JSON = "side_merge.json"
TIMINGS_JSON = "timings.json"
TREES_CSV_COLUMNS = (
    "id",
    "x_m",
    "y_m",
    "z_m",
    "trunk_diameter_m",
    "height_m",
    "canopy_volume_m3",
    "fruit_count",
    "flags",
)
# After those, what a grower compares besides: each trait's 90 % interval, each side's own values, the fruit seen
# from each side, where the canopy begins. Empty where not measured. A reader needs only the columns above.
TREES_CSV_MORE_COLUMNS = (
    "trunk_diameter_lo_m",
    "trunk_diameter_hi_m",
    "height_lo_m",
    "height_hi_m",
    "canopy_volume_lo_m3",
    "canopy_volume_hi_m3",
    "trunk_diameter_front_m",
    "trunk_diameter_back_m",
    "height_front_m",
    "height_back_m",
    "fruit_count_front",
    "fruit_count_back",
    "fruit_on_ground",
    "clear_trunk_height_m",
)
TREES_FRAMES = ("map", "odom_front")  # frames trees.json may state (map == odom_front after merging)
_TREE_KEYS = {
    "id",
    "position",
    "trunk_diameter_m",
    "height_m",
    "canopy_volume_m3",
    "fruit_count",
    "fruit_positions",
    "per_side",
    "flags",
}


def trajectory_filename(side: str) -> str:
    """`trajectory_<side>.tum`."""
    return f"trajectory_{side}.tum"


def map_trajectory_filename(side: str) -> str:
    """`trajectory_<side>_map.tum`: the side's keyframes in `map` after the merge."""
    return f"trajectory_{side}_map.tum"


# ---------------------------------------------------------------- atomic writing


def to_jsonable(obj: Any) -> Any:
    """Dataclasses, numpy arrays/scalars, tuples and paths -> plain JSON values."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write `text` (UTF-8) to `path` via a temporary file in the same folder, fsync, rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # make the rename durable where the OS allows it
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    return path


def _dumps(obj: Any, path: Path) -> str:
    try:
        return json.dumps(to_jsonable(obj), indent=2, allow_nan=False) + "\n"
    except (TypeError, ValueError) as err:
        raise ResultFormatError(f"{path}: cannot serialise as JSON: {err}") from err


# errno values that mean the folder cannot take the results, whichever file met them (the message may name none)
_CANNOT_TAKE = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS})


def _output_error(err: OSError, out: Path) -> OutputError | None:
    """The OutputError that `err`, met while a set of results was written into `out`, stands for; None when the
    error is not about `out` (a bag or a model that cannot be read is another error's to say)."""
    name = os.fsdecode(err.filename) if err.filename is not None else None
    inside = False
    if name is not None:
        target, p = out.absolute(), Path(name).absolute()
        inside = p == target or target in p.parents
        name = None if p == target else name  # the folder itself: the message names it already
    if not inside and err.errno not in _CANNOT_TAKE:
        return None
    why = err.strerror or str(err)
    return OutputError(f"cannot write the results: {why}{f' ({name})' if name else ''}; nothing of this run "
                       "was kept there", path=str(out))


@contextlib.contextmanager
def staged_folder(out: str | Path, replaces: Iterable[str] = ()) -> Iterator[Path]:
    """A staging folder inside `out` to write a set of results into; its files move into `out` only when
    the block ends without an error, so a failed or stopped run leaves no half-written set (earlier
    results in `out` stay as they were, and folders this call created are removed again).

    replaces: glob patterns of the files and folders a set of results is made of. Those in `out` that the new
    set does not hold are removed once it has moved in, so that the folder holds one run's results, never a
    mix of two (an earlier run's trunks.json beside a run without trunks); other files are left alone.
    An OSError met writing into `out` (no permission, not a folder, disk full) is raised as OutputError."""
    out = Path(out)
    created = [d for d in (out, *out.parents) if not d.exists()]  # folders made here (deepest first)
    stage: Path | None = None
    try:
        out.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
        yield stage
        written = {f.name for f in stage.iterdir()}
        for f in sorted(stage.iterdir()):
            if f.is_dir() and (out / f.name).is_dir():  # a folder of results (trees/): the earlier one goes
                shutil.rmtree(out / f.name)
            os.replace(f, out / f.name)
        for pattern in replaces:
            for old in out.glob(pattern):
                if old.name not in written and not old.name.startswith(".staging-"):
                    shutil.rmtree(old) if old.is_dir() and not old.is_symlink() else old.unlink()
    except BaseException as err:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)
        for d in created:  # rmdir: only while empty
            try:
                d.rmdir()
            except OSError:
                break
        output_error = _output_error(err, out) if isinstance(err, OSError) else None
        if output_error is not None:
            raise output_error from err
        raise
    finally:
        if stage is not None:
            shutil.rmtree(stage, ignore_errors=True)


def portable_json(obj: Any, **dumps_kw: Any) -> str:
    """json.dumps of a benchmark's results without this machine's paths: the system's temporary folder
    becomes "<tmp>", the home folder "~", and the current folder ".", so a committed results file says
    what was measured, not where."""
    text = json.dumps(obj, **dumps_kw)
    for folder, name in ((Path.cwd(), "."), (Path(tempfile.gettempdir()), "<tmp>"), (Path.home(), "~")):
        quoted = json.dumps(str(folder))[1:-1]  # as it stands inside a JSON string
        text = text.replace(f'"{quoted}/', f'"{name}/').replace(f'"{quoted}"', f'"{name}"')
    return text


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    """Serialise `obj` (strict JSON: no NaN) first, then write it atomically."""
    path = Path(path)
    return atomic_write_text(path, _dumps(obj, path))


def load_json(path: Path, error: type[Exception] = ResultFormatError, what: str = "file") -> Any:
    """The JSON document at path; a missing, unreadable or malformed file raises `error` naming the path."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise error(f"{path}: {what} not found") from err
    except (OSError, UnicodeDecodeError) as err:
        raise error(f"{path}: cannot read: {err}") from err
    except json.JSONDecodeError as err:
        raise error(f"{path}: not valid JSON: {err}") from err


# ---------------------------------------------------------------- trees


@dataclass(frozen=True)
class ResultTree:
    """One estimated tree of trees.json (frame `map`); None = not measured."""

    id: int
    position: tuple[float, float, float]  # m, map: trunk axis at local ground
    trunk_diameter_m: float | None = None  # m
    height_m: float | None = None  # m
    canopy_volume_m3: float | None = None  # m^3
    fruit_count: int | None = None
    fruit_positions: np.ndarray | None = None  # (F, 3) m, map; optional
    per_side: Mapping[str, Any] | None = None  # optional {"front": {...}, "back": {...}}
    flags: tuple[str, ...] = ()
    extra: Mapping[str, Any] = field(default_factory=dict)  # other keys, kept as written

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "id": self.id,
            "position": list(self.position),
            "trunk_diameter_m": self.trunk_diameter_m,
            "height_m": self.height_m,
            "canopy_volume_m3": self.canopy_volume_m3,
            "fruit_count": self.fruit_count,
        }
        if self.fruit_positions is not None:
            out["fruit_positions"] = np.asarray(self.fruit_positions, dtype=float).reshape(-1, 3)
        if self.per_side is not None:
            out["per_side"] = self.per_side
        if self.flags:
            out["flags"] = list(self.flags)
        out.update(self.extra)
        return to_jsonable(out)


def _tree_from_json(obj: Any, path: Path, where: str) -> ResultTree:
    t = as_mapping(obj, path, where)
    pos = as_array(get_field(t, "position", path, where), (3,), path, f"{where}.position")
    fruit = None
    if t.get("fruit_positions") is not None:
        fruit = as_array(t["fruit_positions"], (-1, 3), path, f"{where}.fruit_positions")
    per_side = t.get("per_side")
    if per_side is not None:
        as_mapping(per_side, path, f"{where}.per_side")
    flags = t.get("flags") or []
    if not isinstance(flags, list) or not all(isinstance(f, str) for f in flags):
        raise field_error(path, f"{where}.flags", f"expected a list of strings, got {flags!r}")
    return ResultTree(
        id=as_integer(get_field(t, "id", path, where), path, f"{where}.id"),  # type: ignore[arg-type]
        position=(float(pos[0]), float(pos[1]), float(pos[2])),
        trunk_diameter_m=as_number(
            t.get("trunk_diameter_m"), path, f"{where}.trunk_diameter_m", nullable=True, minimum=0
        ),
        height_m=as_number(t.get("height_m"), path, f"{where}.height_m", nullable=True, minimum=0),
        canopy_volume_m3=as_number(
            t.get("canopy_volume_m3"), path, f"{where}.canopy_volume_m3", nullable=True, minimum=0
        ),
        fruit_count=as_integer(t.get("fruit_count"), path, f"{where}.fruit_count", nullable=True, minimum=0),
        fruit_positions=fruit,
        per_side=per_side,
        flags=tuple(flags),
        extra={k: v for k, v in t.items() if k not in _TREE_KEYS},
    )


def _trees_from_document(doc: Any, path: Path) -> list[ResultTree]:
    d = as_mapping(doc, path, "")
    schema = get_field(d, "schema", path, "")
    if schema != RESULT_SCHEMA:
        raise field_error(path, "schema", f"expected {RESULT_SCHEMA!r}, got {schema!r}")
    frame = get_field(d, "frame", path, "")
    if frame not in TREES_FRAMES:
        raise field_error(path, "frame", f"expected one of {TREES_FRAMES}, got {frame!r}")
    trees = get_field(d, "trees", path, "")
    if not isinstance(trees, list):
        raise field_error(path, "trees", f"expected a list, got {type(trees).__name__}")
    out = [_tree_from_json(t, path, f"trees[{i}]") for i, t in enumerate(trees)]
    ids = [t.id for t in out]
    if len(set(ids)) != len(ids):
        raise field_error(path, "trees[].id", f"ids are not unique: {sorted(ids)}")
    return out


def _as_tree_json(tree: ResultTree | Mapping[str, Any] | Any) -> Any:
    if isinstance(tree, ResultTree):
        return tree.to_json()
    return to_jsonable(tree)


def _csv_value(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return repr(v)
    return str(v)


def write_trees(
    result_dir: str | Path, trees: Iterable[ResultTree | Mapping[str, Any] | Any], frame: str = "map"
) -> tuple[Path, Path]:
    """Write trees.json and trees.csv into `result_dir` from ResultTree, dicts or dataclasses.

    The trees are validated first (ResultFormatError, nothing written).
    Returns (json path, csv path).
    """
    result_dir = Path(result_dir)
    json_path, csv_path = result_dir / TREES_JSON, result_dir / TREES_CSV
    doc = {"schema": RESULT_SCHEMA, "frame": frame, "trees": [_as_tree_json(t) for t in trees]}
    text = _dumps(doc, json_path)
    parsed = _trees_from_document(json.loads(text), json_path)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(TREES_CSV_COLUMNS + TREES_CSV_MORE_COLUMNS)
    for t in parsed:
        w.writerow(
            [t.id, *(repr(p) for p in t.position)]
            + [_csv_value(v) for v in (t.trunk_diameter_m, t.height_m, t.canopy_volume_m3, t.fruit_count)]
            + [";".join(t.flags)]
            + [_csv_value(v) for v in _more_values(t)]
        )
    atomic_write_text(json_path, text)
    atomic_write_text(csv_path, buf.getvalue())
    return json_path, csv_path


def _more_values(t: ResultTree) -> list[Any]:
    """The TREES_CSV_MORE_COLUMNS of a tree (None where trees.json has no such value)."""
    iv = t.extra.get("interval_90") or {}
    side = t.per_side or {}

    def bound(trait: str, k: int) -> Any:
        b = iv.get(trait)
        return b[k] if isinstance(b, (list, tuple)) and len(b) == 2 else None

    def own(s: str, key: str) -> Any:
        v = side.get(s)
        return v.get(key) if isinstance(v, dict) else None

    return [bound("trunk_diameter_m", 0), bound("trunk_diameter_m", 1), bound("height_m", 0), bound("height_m", 1),
            bound("canopy_volume_m3", 0), bound("canopy_volume_m3", 1),
            own("front", "diameter_m"), own("back", "diameter_m"), own("front", "height_m"), own("back", "height_m"),
            t.extra.get("fruit_count_front"), t.extra.get("fruit_count_back"), t.extra.get("fruit_on_ground"),
            t.extra.get("clear_trunk_height_m")]


def read_trees(path: str | Path) -> list[ResultTree]:
    """Read and validate trees.json (a file, or a result folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / TREES_JSON
    return _trees_from_document(load_json(path), path)


def read_trees_csv(path: str | Path) -> list[ResultTree]:
    """Read trees.csv (a file, or a result folder holding it); empty cells = None."""
    path = Path(path)
    if path.is_dir():
        path = path / TREES_CSV
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as err:
        raise ResultFormatError(f"{path}: file not found") from err
    rows = list(csv.reader(io.StringIO(text)))
    if not rows or tuple(rows[0][: len(TREES_CSV_COLUMNS)]) != TREES_CSV_COLUMNS:
        raise ResultFormatError(f"{path}:1: expected header {','.join(TREES_CSV_COLUMNS)}")
    width = len(rows[0])
    out = []
    for lineno, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        if len(row) != width:
            raise ResultFormatError(f"{path}:{lineno}: expected {width} columns, got {len(row)}")
        try:
            vals = [None if c == "" else float(c) for c in row[1:8]]
            tid = int(row[0])
        except ValueError as err:
            raise ResultFormatError(f"{path}:{lineno}: {err}") from err
        if any(v is None for v in vals[:3]) or not all(math.isfinite(v) for v in vals if v is not None):
            raise ResultFormatError(f"{path}:{lineno}: position missing or a value is not finite")
        out.append(
            ResultTree(
                id=tid,
                position=(vals[0], vals[1], vals[2]),  # type: ignore[arg-type]
                trunk_diameter_m=vals[3],
                height_m=vals[4],
                canopy_volume_m3=vals[5],
                fruit_count=None if vals[6] is None else int(vals[6]),
                flags=tuple(f for f in row[8].split(";") if f),
            )
        )
    return out


# ---------------------------------------------------------------- TUM trajectories


def _check_trajectory(traj: StampedTrajectory, path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    stamps = np.asarray(traj.stamps, dtype=float).reshape(-1)
    pos = np.asarray(traj.positions, dtype=float)
    quat = np.asarray(traj.quaternions, dtype=float)
    n = stamps.shape[0]
    if pos.shape != (n, 3) or quat.shape != (n, 4):
        raise ResultFormatError(f"{path}: trajectory shapes {stamps.shape}, {pos.shape}, {quat.shape} do not agree")
    if not (np.all(np.isfinite(stamps)) and np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise ResultFormatError(f"{path}: trajectory holds a non-finite value")
    if np.any(np.linalg.norm(quat, axis=1) < 1e-12):
        raise ResultFormatError(f"{path}: trajectory holds a zero quaternion")
    if np.any(np.diff(stamps) <= 0.0):
        raise ResultFormatError(f"{path}: trajectory stamps are not strictly increasing")
    return stamps, pos, quat


def write_tum(path: str | Path, traj: StampedTrajectory) -> Path:
    """Write `stamp tx ty tz qx qy qz qw` lines (s, m, unit quaternion) with a `#` header."""
    path = Path(path)
    stamps, pos, quat = _check_trajectory(traj, path)
    quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    lines = [f"# stamp tx ty tz qx qy qz qw (camera in {traj.frame_id or 'odom'})"]
    rows = np.column_stack([stamps, pos, quat])  # (N, 8)
    lines += [" ".join(repr(float(v)) for v in row) for row in rows]
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_tum(path: str | Path, frame_id: str = "") -> StampedTrajectory:
    """Read a TUM file; `#` comments and blank lines are skipped; quaternions normalised.

    Raises ResultFormatError naming `file:line` for a malformed line, and for
    an empty trajectory or stamps that do not increase.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as err:
        raise ResultFormatError(f"{path}: file not found") from err
    except (OSError, UnicodeDecodeError) as err:
        raise ResultFormatError(f"{path}: cannot read: {err}") from err
    rows: list[list[float]] = []
    last = -math.inf
    for lineno, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise ResultFormatError(
                f"{path}:{lineno}: expected 8 numbers 'stamp tx ty tz qx qy qz qw', got {len(parts)}"
            )
        try:
            vals = [float(p) for p in parts]
        except ValueError as err:
            raise ResultFormatError(f"{path}:{lineno}: not a number: {err}") from err
        if not all(math.isfinite(v) for v in vals):
            raise ResultFormatError(f"{path}:{lineno}: non-finite value")
        if math.fsum(v * v for v in vals[4:]) < 1e-24:
            raise ResultFormatError(f"{path}:{lineno}: zero quaternion")
        if vals[0] <= last:
            raise ResultFormatError(f"{path}:{lineno}: stamp {vals[0]!r} does not increase")
        last = vals[0]
        rows.append(vals)
    if not rows:
        raise ResultFormatError(f"{path}: no poses")
    a = np.asarray(rows)  # (N, 8)
    quat = a[:, 4:8] / np.linalg.norm(a[:, 4:8], axis=1, keepdims=True)
    return StampedTrajectory(stamps=a[:, 0].copy(), positions=a[:, 1:4].copy(), quaternions=quat, frame_id=frame_id)


# ---------------------------------------------------------------- side_merge.json


@dataclass(frozen=True)
class SideMerge:
    """side_merge.json: the similarity mapping odom_back points into odom_front (map)."""

    T_front_back: np.ndarray  # (4, 4), 3x3 block = s R
    scale: float  # s
    residuals: Mapping[str, Any] = field(default_factory=dict)
    overlap: Any = None
    extra: Mapping[str, Any] = field(default_factory=dict)


def _similarity_scale(T: np.ndarray, path: Path, where: str) -> float:
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
        raise field_error(path, where, f"last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    det = float(np.linalg.det(T[:3, :3]))
    if det <= 1e-12:
        raise field_error(path, where, f"3x3 block is singular or a reflection (det = {det:.3g})")
    return det ** (1.0 / 3.0)


def write_side_merge(
    path: str | Path,
    T_front_back: np.ndarray,
    *,
    residuals: Mapping[str, Any] | None = None,
    overlap: Any = None,
    **extra: Any,
) -> Path:
    """Write side_merge.json; `scale` = cbrt(det) of the 3x3 block of T_front_back."""
    path = Path(path)
    T = as_array(T_front_back, (4, 4), path, "T_front_back")
    doc = {
        "T_front_back": T,
        "scale": _similarity_scale(T, path, "T_front_back"),
        "residuals": dict(residuals or {}),
        "overlap": overlap,
        **extra,
    }
    return atomic_write_json(path, doc)


def read_side_merge(path: str | Path) -> SideMerge:
    """Read and validate side_merge.json (a file, or a result folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / SIDE_MERGE_JSON
    d = as_mapping(load_json(path), path, "")
    T = as_array(get_field(d, "T_front_back", path, ""), (4, 4), path, "T_front_back")
    s_matrix = _similarity_scale(T, path, "T_front_back")
    s = as_number(d.get("scale", s_matrix), path, "scale", minimum=0.0)
    assert s is not None
    if abs(s - s_matrix) > 1e-4 * s_matrix:
        raise field_error(path, "scale", f"{s!r} disagrees with the scale of T_front_back ({s_matrix:.6g})")
    residuals = d.get("residuals") or {}
    as_mapping(residuals, path, "residuals")
    known = {"T_front_back", "scale", "residuals", "overlap"}
    return SideMerge(
        T_front_back=T,
        scale=s,
        residuals=residuals,
        overlap=d.get("overlap"),
        extra={k: v for k, v in d.items() if k not in known},
    )


# ---------------------------------------------------------------- timings.json


@dataclass(frozen=True)
class Timings:
    """timings.json: processing seconds per stage (in run order)."""

    stages: Mapping[str, float]  # s
    frames: int | None = None
    recording_duration_s: float | None = None  # s
    # s, the run's wall clock: less than the stages' sum where stages overlap (the trunk detector's thread beside
    # the front end, a side's trunk modelling in a worker process); None in files from before it was written
    wall_s: float | None = None
    # s per step of the merge (alignment, initial_transform, semantic_ba): a breakdown of the `merge` stage, kept
    # here and not in side_merge.json, so that every file but this one is the same on every run of a recording
    merge_steps: Mapping[str, float] = dataclasses.field(default_factory=dict)

    @property
    def total_s(self) -> float:
        return float(math.fsum(self.stages.values()))

    @property
    def elapsed_s(self) -> float:
        """The run's wall clock where the file gives it, else the stages' sum."""
        return self.wall_s if self.wall_s is not None else self.total_s


def write_timings(
    path: str | Path, stages: Mapping[str, float], frames: int | None = None, recording_duration_s: float | None = None,
    wall_s: float | None = None, merge_steps: Mapping[str, float] | None = None,
) -> Path:
    """Write timings.json (validated first)."""
    path = Path(path)
    doc: dict[str, Any] = {
        "stages": {str(k): float(v) for k, v in stages.items()},
        "frames": frames,
        "recording_duration_s": recording_duration_s,
    }
    if wall_s is not None:
        doc["wall_s"] = float(wall_s)
    if merge_steps:
        doc["merge_steps"] = {str(k): float(v) for k, v in merge_steps.items()}
    _timings_from_document(json.loads(_dumps(doc, path)), path)
    return atomic_write_json(path, doc)


def _timings_from_document(doc: Any, path: Path) -> Timings:
    d = as_mapping(doc, path, "")
    stages = as_mapping(get_field(d, "stages", path, ""), path, "stages")
    parsed = {str(k): as_number(v, path, f"stages.{k}", minimum=0.0) for k, v in stages.items()}
    frames = as_integer(d.get("frames"), path, "frames", nullable=True, minimum=0)
    rec = as_number(d.get("recording_duration_s"), path, "recording_duration_s", nullable=True, minimum=0.0)
    wall = as_number(d.get("wall_s"), path, "wall_s", nullable=True, minimum=0.0)
    steps = as_mapping(d.get("merge_steps") or {}, path, "merge_steps")
    merge_steps = {str(k): as_number(v, path, f"merge_steps.{k}", minimum=0.0) for k, v in steps.items()}
    return Timings(stages=parsed, frames=frames, recording_duration_s=rec, wall_s=wall,  # type: ignore[arg-type]
                   merge_steps=merge_steps)  # type: ignore[arg-type]


def read_timings(path: str | Path) -> Timings:
    """Read and validate timings.json (a file, or a result folder holding it)."""
    path = Path(path)
    if path.is_dir():
        path = path / TIMINGS_JSON
    return _timings_from_document(load_json(path), path)
