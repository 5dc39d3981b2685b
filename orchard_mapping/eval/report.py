"""The evaluation report: frozen sections, `to_dict()` for JSON and rich tables for humans."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from rich.table import Table

from orchard_mapping.eval.metrics import DoubleCount, MergeError, TrajectoryError

__all__ = [
    "EVALUATION_SCHEMA",
    "EvaluationReport",
    "FruitCountError",
    "MatchingSummary",
    "TimingSummary",
    "TraitErrors",
    "TreePair",
]

EVALUATION_SCHEMA = "orchard_mapping.evaluation/1"


@dataclass(frozen=True)
class TreePair:
    """A matched (true, estimated) tree; estimates None where not measured."""

    true_id: int
    result_id: int
    distance_m: float  # m, 3D in map
    true_trunk_diameter_m: float
    est_trunk_diameter_m: float | None
    true_height_m: float
    est_height_m: float | None
    true_canopy_volume_m3: float
    est_canopy_volume_m3: float | None
    true_fruit_visible: int  # visible from either side
    true_fruit_all: int
    est_fruit_count: int | None


@dataclass(frozen=True)
class MatchingSummary:
    true_trees: int
    result_trees: int
    matched: int
    missed: int
    false: int
    mean_distance_m: float | None  # m, over matched pairs
    missed_ids: tuple[int, ...]  # true tree ids
    false_ids: tuple[int, ...]  # result tree ids
    # mm: RMS distance of the matched trees after one rigid alignment of all of them to the truth (the map's
    # shape, whatever its placement); None with fewer than 3 matched trees
    position_rmse_mm: float | None = None


@dataclass(frozen=True)
class TraitErrors:
    """Over matched trees whose estimate is not null (n_* says how many)."""

    trunk_diameter_mae_mm: float | None
    trunk_diameter_n: int
    height_mae_cm: float | None
    height_n: int
    canopy_volume_mape_percent: float | None  # mean |est - true| / true x 100
    canopy_volume_bias_percent: float | None  # mean (est - true) / true x 100
    canopy_volume_n: int
    # trait -> {"n": trees whose result gives a 90 % interval, "coverage": share of them holding the truth}
    interval_coverage: Mapping[str, Mapping[str, float]] = field(default_factory=dict)


@dataclass(frozen=True)
class FruitCountError:
    """Summed over matched trees with a non-null fruit_count."""

    n_trees: int
    estimated: int
    true_visible: int  # fruit visible from either side
    true_all: int
    error_visible_percent: float | None  # (est - visible) / visible x 100
    error_all_percent: float | None  # (est - all) / all x 100


@dataclass(frozen=True)
class TimingSummary:
    stages: Mapping[str, float]  # s per stage
    total_s: float  # s, sum of the stages
    frames: int | None
    recording_duration_s: float | None  # s
    recording_duration_source: str  # "timings.json", "ground truth" or "unknown"
    realtime_factor: float | None  # elapsed_s / recording_duration_s (< 1 = faster than real time)
    # s, the run's wall clock (timings.json's wall_s; the stages' sum where the file has none): stages overlap
    elapsed_s: float | None = None


def _plain(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _fmt(v: float | None, digits: int = 2, signed: bool = False) -> str:
    if v is None:
        return "n/a"
    return f"{v:+.{digits}f}" if signed else f"{v:.{digits}f}"


def _fmt_count(v: int | None) -> str:
    return "n/a" if v is None else str(v)


@dataclass(frozen=True)
class EvaluationReport:
    """Every metric of one result folder against one ground truth; None = not evaluated (see `skipped`)."""

    truth_path: Path
    result_dir: Path
    match_radius_m: float  # m
    matching: MatchingSummary | None
    traits: TraitErrors | None
    fruit_count: FruitCountError | None
    double_count: DoubleCount | None
    merge: MergeError | None  # the merge's rigid odom_back -> odom_front against the true one
    sides: Mapping[str, TrajectoryError | None]
    timings: TimingSummary | None
    pairs: tuple[TreePair, ...] = ()
    skipped: Mapping[str, str] = field(default_factory=dict)  # part -> reason
    trunks: Mapping[str, Any] = field(default_factory=dict)  # side -> eval.landmarks.TrunkErrors
    grounds: Mapping[str, Any] = field(default_factory=dict)  # side -> eval.landmarks.GroundErrors
    # After the merge: distance between the two sides' axes of each paired trunk at the diameter height, in
    # map (mm): {"median", "max", "n"}; None when there is no merge to measure.
    trunk_axis_gap_mm: Mapping[str, float] | None = None
    # The merged map's placement of the back side against the front side, each side's drift left out
    # (eval.metrics.map_merge_error); None without both sides' trajectories in map.
    merge_map: MergeError | None = None
    # The same with each side's keyframes limited to the sweep that saw its trunks (its first to its last
    # trunk observation): what the merge placed, a side's other sweeps' own drift left out.
    merge_map_trunk_sweep: MergeError | None = None
    # Each point of trees.laz against the tree whose surface it lies on (eval.segmentation); None without
    # the simulator's tree_surfaces.npz or the result's trees.laz.
    segmentation: Any = None

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable; every key is always present (null where not evaluated)."""
        return {
            "schema": EVALUATION_SCHEMA,
            "truth": str(self.truth_path),
            "result": str(self.result_dir),
            "match_radius_m": self.match_radius_m,
            "matching": _plain(self.matching),
            "traits": _plain(self.traits),
            "fruit_count": _plain(self.fruit_count),
            "double_count": _plain(self.double_count),
            "segmentation": _plain(self.segmentation),
            "merge": None if self.merge is None else {**_plain(self.merge),
                                                      "trunk_axis_gap_mm": self.trunk_axis_gap_mm,
                                                      "map": _plain(self.merge_map),
                                                      "map_trunk_sweep": _plain(self.merge_map_trunk_sweep)},
            "trees": {"position_rmse_mm": None if self.matching is None else self.matching.position_rmse_mm},
            "sides": {name: _plain(err) for name, err in self.sides.items()},
            "trunks": {name: _plain(e) for name, e in self.trunks.items()},
            "grounds": {name: _plain(e) for name, e in self.grounds.items()},
            "timings": _plain(self.timings),
            "per_tree": [_plain(p) for p in self.pairs],
            "skipped": dict(self.skipped),
        }

    def rows(self) -> list[tuple[str, str, str, str]]:
        """(metric, value, unit, note) rows of `table()`."""
        rows: list[tuple[str, str, str, str]] = []
        skip = self.skipped

        def na(metric: str, part: str) -> None:
            rows.append((metric, "n/a", "", skip.get(part, "not evaluated")))

        m = self.matching
        if m is None:
            na("trees matched", "matching")
        else:
            note = f"3D distance <= {self.match_radius_m:g} m in map; mean {_fmt(m.mean_distance_m, 3)} m"
            rows += [
                ("trees matched", f"{m.matched}/{m.true_trees}", "trees", note),
                ("tree position RMSE", _fmt(m.position_rmse_mm, 1), "mm",
                 "matched trees after one rigid alignment to the truth"),
                ("trees missed", str(m.missed), "trees", f"true ids {list(m.missed_ids)}" if m.missed else ""),
                ("false trees", str(m.false), "trees", f"result ids {list(m.false_ids)}" if m.false else ""),
            ]
        t = self.traits
        if t is None:
            for name in ("trunk diameter MAE", "height MAE", "canopy volume error"):
                na(name, "traits")
        else:
            rows += [
                ("trunk diameter MAE", _fmt(t.trunk_diameter_mae_mm), "mm", f"{t.trunk_diameter_n} matched trees"),
                ("height MAE", _fmt(t.height_mae_cm), "cm", f"{t.height_n} matched trees"),
                (
                    "canopy volume error",
                    _fmt(t.canopy_volume_mape_percent, 1),
                    "%",
                    f"mean absolute; signed {_fmt(t.canopy_volume_bias_percent, 1, True)} %; {t.canopy_volume_n} trees",
                ),
            ]
        sg = self.segmentation
        if sg is None:
            na("segmentation accuracy", "segmentation")
        else:
            rows += [
                ("segmentation accuracy", _fmt(100.0 * sg.accuracy, 1), "%",
                 f"{sg.n_points} points on matched trees' surfaces (within {100 * sg.tolerance_m:g} cm); "
                 f"{_fmt(100.0 * sg.unassigned, 1)} % given to no tree"),
                ("segmentation accuracy where crowns touch",
                 "n/a" if sg.accuracy_near_neighbour is None else _fmt(100.0 * sg.accuracy_near_neighbour, 1), "%",
                 f"{sg.n_near_neighbour} points with another tree's surface within 0.3 m"),
            ]
        f = self.fruit_count
        if f is None:
            na("fruit count error (visible)", "fruit_count")
        else:
            rows += [
                (
                    "fruit count error (visible)",
                    _fmt(f.error_visible_percent, 1, True),
                    "%",
                    f"{f.estimated} est vs {f.true_visible} visible from either side; {f.n_trees} trees",
                ),
                ("fruit count error (all)", _fmt(f.error_all_percent, 1, True), "%", f"vs {f.true_all} fruit in total"),
            ]
        d = self.double_count
        if d is None:
            na("double-count rate", "double_count")
        else:
            rows.append(
                (
                    "double-count rate",
                    _fmt(d.rate_percent, 1),
                    "%",
                    f"{d.duplicates} of {d.estimated} estimated fruit; {d.false} matched no true fruit",
                )
            )
            rows += [
                ("fruit counted twice", _fmt(d.per_both_percent, 1), "%", "duplicates per true fruit seen from both sides"),
                ("fruit position error", _fmt(d.position_error_median_mm, 1), "mm", f"median over {d.matched} matched"),
                ("fruit diameter MAE", _fmt(d.diameter_mae_mm, 1), "mm",
                 f"signed {_fmt(d.diameter_bias_mm, 1, True)} mm"),
            ]
        g = self.merge
        if g is None:
            na("merge rotation error", "merge")
        else:
            rows += [
                ("merge rotation error", _fmt(g.rotation_error_deg, 3), "deg", "odom_back -> odom_front vs truth, scale removed"),
                (
                    "merge translation error",
                    _fmt(g.translation_error_mm, 1),
                    "mm",
                    f"mean over {g.n_points} trunk bases; max {_fmt(g.max_translation_error_mm, 1)} mm",
                ),
            ]
            m = self.merge_map
            if m is not None:
                rows += [("merged map rotation error", _fmt(m.rotation_error_deg, 3), "deg",
                          "back side vs front side in map, each fitted to its truth"),
                         ("merged map translation error", _fmt(m.translation_error_mm, 1), "mm",
                          f"mean over {m.n_points} trunk bases; max {_fmt(m.max_translation_error_mm, 1)} mm")]
            ms = self.merge_map_trunk_sweep
            if ms is not None:
                rows.append(("merged map error, trunk-seeing sweeps", f"{_fmt(ms.rotation_error_deg, 3)} / "
                             f"{_fmt(ms.translation_error_mm, 1)}", "deg / mm",
                             "each side's keyframes from its first to its last trunk observation"))
            gap = self.trunk_axis_gap_mm
            if gap is not None:
                rows.append(("trunk axis gap after the merge", _fmt(gap["median"], 1), "mm",
                             f"median over {gap['n']} trunks seen from both sides; max {_fmt(gap['max'], 1)} mm"))
            if g.scale_error_percent is not None:
                rows.append(("merge scale error", _fmt(g.scale_error_percent, 2, True), "%", f"scale {g.scale:.5f}"))
        for name, e in self.sides.items():
            if e is None:
                na(f"{name} trajectory", f"sides.{name}")
                continue
            span = f"{e.n_associated} poses over {_fmt(e.path_length_m)} m"
            rows += [
                (f"{name} drift", _fmt(e.drift_percent), "% of path", f"{_fmt(e.drift_mm, 1)} mm at the end; {span}"),
                (
                    f"{name} ATE",
                    _fmt(e.ate_percent),
                    "% of path",
                    f"{_fmt(e.ate_mm, 1)} mm RMSE, {e.alignment} alignment",
                ),
            ]
        for name, te in self.trunks.items():
            if te is None:
                na(f"{name} trunks", f"trunks.{name}")
                continue
            rows += [
                (f"{name} trunk recall", _fmt(None if te.recall is None else 100 * te.recall, 1), "%",
                 f"{te.matched} matched of {te.true_in_view} in view at the diameter height"),
                (f"{name} trunk precision", _fmt(None if te.precision is None else 100 * te.precision, 1), "%",
                 f"{te.reported} reported, {te.hidden_reported} hidden at the diameter height"),
                (f"{name} trunk diameter MAE", _fmt(te.diameter_mae_mm), "mm",
                 f"bias {_fmt(te.diameter_bias_mm, 2, True)} mm over {te.diameter_n}; 3D-only fit: MAE "
                 f"{_fmt(te.diameter_3d_only_mae_mm)}, bias {_fmt(te.diameter_3d_only_bias_mm, 2, True)} mm"),
                (f"{name} trunk axis error", _fmt(te.axis_error_deg), "deg", "median"),
            ]
        for name, ge in self.grounds.items():
            if ge is None or ge.n == 0:
                na(f"{name} local grounds", f"grounds.{name}")
                continue
            rows += [
                (f"{name} ground normal error", _fmt(ge.normal_error_deg_median), "deg",
                 f"median, max {_fmt(ge.normal_error_deg_max)} over {ge.n} trees, vs the {ge.reference} ground; "
                 f"vs the full disk {_fmt(ge.normal_error_full_deg_median)}"),
                (f"{name} ground height error", _fmt(ge.height_error_mm_median, 1), "mm",
                 f"median, max {_fmt(ge.height_error_mm_max, 1)}; vs the full disk "
                 f"{_fmt(ge.height_error_full_mm_median, 1)}"),
            ]
        tm = self.timings
        if tm is None:
            na("processing time", "timings")
        else:
            rows += [(f"time: {k}", _fmt(v), "s", "") for k, v in tm.stages.items()]
            rows.append(("time: sum of the stages", _fmt(tm.total_s), "s",
                         f"{tm.frames} frames" if tm.frames is not None else ""))
            if tm.elapsed_s is not None and tm.elapsed_s != tm.total_s:
                rows.append(("time: wall clock", _fmt(tm.elapsed_s), "s", "stages overlap"))
            rows.append(
                (
                    "real-time factor",
                    _fmt(tm.realtime_factor),
                    "x",
                    f"processing / recording ({_fmt(tm.recording_duration_s, 1)} s, {tm.recording_duration_source})",
                )
            )
        return rows

    def table(self) -> Table:
        """One rich table: metric, value, unit, note."""
        tab = Table(title=f"evaluation of {self.result_dir}")
        tab.add_column("metric")
        tab.add_column("value", justify="right")
        tab.add_column("unit")
        tab.add_column("note")
        for row in self.rows():
            tab.add_row(*row)
        return tab

    def trunk_table(self) -> Table:
        """Per side, each matched trunk: true and estimated diameter (and the 3D-only fit)."""
        tab = Table(title="trunks per side (true / estimated; 3D-only fit)")
        for name in ("side", "tree", "trunk", "diameter (mm)", "3D-only (mm)", "axis err (deg)", "flags"):
            tab.add_column(name, justify="left" if name in ("side", "flags") else "right")
        for side, te in self.trunks.items():
            for p in te.pairs if te is not None else ():
                tab.add_row(side, str(p.true_id), str(p.trunk_id),
                            f"{p.diameter_true_mm:.1f} / {_fmt(p.diameter_mm, 1)}", _fmt(p.diameter_3d_only_mm, 1),
                            f"{p.axis_error_deg:.2f}", ", ".join(p.flags))
        return tab

    def per_tree_table(self) -> Table:
        """True vs estimated values per matched tree."""
        tab = Table(title="matched trees (true / estimated)")
        for name, justify in (
            ("true id", "right"),
            ("result id", "right"),
            ("dist (m)", "right"),
            ("diameter (mm)", "right"),
            ("height (m)", "right"),
            ("volume (m^3)", "right"),
            ("fruit visible / all / est", "right"),
        ):
            tab.add_column(name, justify=justify)  # type: ignore[arg-type]

        def pair(a: float, b: float | None, scale: float, digits: int) -> str:
            return f"{a * scale:.{digits}f} / {_fmt(None if b is None else b * scale, digits)}"

        for p in self.pairs:
            tab.add_row(
                str(p.true_id),
                str(p.result_id),
                f"{p.distance_m:.3f}",
                pair(p.true_trunk_diameter_m, p.est_trunk_diameter_m, 1000.0, 1),
                pair(p.true_height_m, p.est_height_m, 1.0, 2),
                pair(p.true_canopy_volume_m3, p.est_canopy_volume_m3, 1.0, 2),
                f"{p.true_fruit_visible} / {p.true_fruit_all} / {_fmt_count(p.est_fruit_count)}",
            )
        return tab
