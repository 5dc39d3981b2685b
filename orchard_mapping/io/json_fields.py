"""Validation of the fields of the result JSON files (io.results, io.landmarks): each helper checks one value
read from `path` at the dotted field `where` and raises `ResultFormatError` naming both."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from orchard_mapping.errors import ResultFormatError


def field_error(path: Path, where: str, msg: str) -> ResultFormatError:
    return ResultFormatError(f"{path}: field '{where}': {msg}")


def get_field(obj: Mapping[str, Any], key: str, path: Path, where: str) -> Any:
    if key not in obj:
        raise field_error(path, f"{where}.{key}" if where else key, "missing")
    return obj[key]


def as_mapping(v: Any, path: Path, where: str) -> Mapping[str, Any]:
    if not isinstance(v, Mapping):
        raise field_error(path, where or "<root>", f"expected an object, got {type(v).__name__}")
    return v


def as_number(v: Any, path: Path, where: str, *, nullable: bool = False, minimum: float | None = None) -> float | None:
    if v is None and nullable:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise field_error(path, where, f"expected a finite number{' or null' if nullable else ''}, got {v!r}")
    if minimum is not None and v < minimum:
        raise field_error(path, where, f"must be >= {minimum}, got {v!r}")
    return float(v)


def as_integer(v: Any, path: Path, where: str, *, nullable: bool = False, minimum: int | None = None) -> int | None:
    if v is None and nullable:
        return None
    if isinstance(v, float) and v.is_integer():
        v = int(v)
    if isinstance(v, bool) or not isinstance(v, int):
        raise field_error(path, where, f"expected an integer{' or null' if nullable else ''}, got {v!r}")
    if minimum is not None and v < minimum:
        raise field_error(path, where, f"must be >= {minimum}, got {v!r}")
    return int(v)


def as_array(v: Any, shape: tuple[int, ...], path: Path, where: str) -> np.ndarray:
    """Finite float array of `shape` (-1 = any length)."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError) as err:
        raise field_error(path, where, f"expected numbers of shape {shape}: {err}") from err
    if a.size == 0 and -1 in shape:
        a = a.reshape(tuple(0 if s == -1 else s for s in shape))
    if a.ndim != len(shape) or any(s != -1 and s != n for s, n in zip(shape, a.shape, strict=True)):
        raise field_error(path, where, f"expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise field_error(path, where, "contains a non-finite value")
    return a
