"""Trunk landmarks and local grounds <-> orchard_mapping_msgs (TrunkCylinder(Array), LocalGround(Array)); the
local_ground_fitter's answer (core.trunks.TrunkGround per landmark) <-> LocalGroundArray, exactly (float64).

`tree_id` carries the per-side trunk id until the side merge assigns tree ids (the ground of a trunk
has the same id, which pairs them). Lengths in metres, in the frame of the array's header.
A trunk hidden at the diameter height has radius NaN (and fit_rmse NaN): the cylinder's axis and base
are known, its radius is not.
"""

from __future__ import annotations

import array
import math
from dataclasses import dataclass

import numpy as np

from orchard_mapping.core.cylinder import Cylinder
from orchard_mapping.core.ground import LocalGroundFit
from orchard_mapping.core.trunks import TrunkGround, TrunkLandmark
from orchard_mapping.errors import OrchardMappingError
from orchard_mapping.io.results import ResultTree

__all__ = ["GroundMessageError", "GroundRecord", "TrunkRecord", "ground_records", "grounds_from_msg", "grounds_to_msg",
           "stamp_header", "trees_from_msg", "trees_to_msg", "trunk_grounds_from_msg", "trunk_grounds_to_msg",
           "trunks_from_msg", "trunks_to_msg"]


class GroundMessageError(OrchardMappingError, ValueError):
    """A LocalGroundArray that is not a ground fitter's answer (names the ground and what is wrong)."""


@dataclass(frozen=True)
class TrunkRecord:
    """One TrunkCylinder message as plain values."""

    tree_id: int
    side: str
    base: tuple[float, float, float]  # m
    axis: tuple[float, float, float]  # unit
    radius: float  # m, NaN when unknown
    length: float  # m
    radius_stddev: float  # m, NaN when unknown
    fit_rmse: float  # m, NaN when unknown
    inlier_count: int
    flags: tuple[str, ...] = ()  # the landmark's flags (trunks.json)

    @staticmethod
    def from_landmark(lm: TrunkLandmark, side: str) -> "TrunkRecord":
        band = lm.band
        return TrunkRecord(lm.id, side, _t3(lm.base), _t3(lm.axis),
                           band.cylinder.radius if band is not None else math.nan, float(lm.length_m), math.nan,
                           band.rmse_3d_m if band is not None else math.nan,
                           band.inliers_3d if band is not None else lm.n_points, tuple(lm.flags))


@dataclass(frozen=True)
class GroundRecord:
    """One LocalGround message as plain values."""

    tree_id: int
    side: str
    point: tuple[float, float, float]  # m
    normal: tuple[float, float, float]  # unit, up
    offset: float  # m, n . p + offset = 0
    fit_rmse: float  # m
    inlier_count: int


def _t3(v: np.ndarray) -> tuple[float, float, float]:
    a = np.asarray(v, float).ravel()
    return (float(a[0]), float(a[1]), float(a[2]))


def stamp_header(header, stamp: float, frame_id: str) -> None:
    """Set a std_msgs/Header (rclpy's): message time `stamp` (s) and frame_id."""
    header.frame_id = frame_id
    sec = math.floor(stamp)
    header.stamp.sec = int(sec)
    header.stamp.nanosec = min(int(round((stamp - sec) * 1e9)), 999_999_999)


def _array_msg(array_cls, item_cls, field: str, records: list, frame_id: str, stamp: float, fill):
    """An array message (header + a list field) with one item per record, each filled by fill(item, record)."""
    out = array_cls()
    stamp_header(out.header, stamp, frame_id)
    for r in records:
        m = item_cls()
        m.header = out.header
        m.tree_id, m.side = int(r.tree_id), r.side
        fill(m, r)
        getattr(out, field).append(m)
    return out


def _fill_trunk(m, r: TrunkRecord) -> None:
    m.base.x, m.base.y, m.base.z = r.base
    m.axis.x, m.axis.y, m.axis.z = r.axis
    m.radius, m.length, m.radius_stddev, m.fit_rmse = r.radius, r.length, r.radius_stddev, r.fit_rmse
    m.inlier_count = int(r.inlier_count)
    m.flags = list(r.flags)


def _fill_ground(m, r: GroundRecord) -> None:
    m.point.x, m.point.y, m.point.z = r.point
    m.normal.x, m.normal.y, m.normal.z = r.normal
    m.offset, m.fit_rmse, m.inlier_count = r.offset, r.fit_rmse, int(r.inlier_count)
    m.kind = "local"


def trunks_to_msg(records: list[TrunkRecord], frame_id: str, stamp: float):
    """TrunkCylinderArray with one cylinder per record (message time `stamp`, s)."""
    from orchard_mapping_msgs.msg import TrunkCylinder, TrunkCylinderArray

    return _array_msg(TrunkCylinderArray, TrunkCylinder, "cylinders", records, frame_id, stamp, _fill_trunk)


def trunks_from_msg(msg) -> tuple[str, float, list[TrunkRecord]]:
    """(frame id, stamp s, records) of a TrunkCylinderArray."""
    recs = [TrunkRecord(int(m.tree_id), str(m.side), (m.base.x, m.base.y, m.base.z), (m.axis.x, m.axis.y, m.axis.z),
                        float(m.radius), float(m.length), float(m.radius_stddev), float(m.fit_rmse),
                        int(m.inlier_count), tuple(str(f) for f in m.flags)) for m in msg.cylinders]
    return msg.header.frame_id, msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, recs


def grounds_to_msg(records: list[GroundRecord], frame_id: str, stamp: float):
    """LocalGroundArray with one plane per record (message time `stamp`, s)."""
    from orchard_mapping_msgs.msg import LocalGround, LocalGroundArray

    return _array_msg(LocalGroundArray, LocalGround, "grounds", records, frame_id, stamp, _fill_ground)


def grounds_from_msg(msg) -> tuple[str, float, list[GroundRecord]]:
    recs = [GroundRecord(int(m.tree_id), str(m.side), (m.point.x, m.point.y, m.point.z),
                         (m.normal.x, m.normal.y, m.normal.z), float(m.offset), float(m.fit_rmse),
                         int(m.inlier_count)) for m in msg.grounds]
    return msg.header.frame_id, msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, recs


def ground_records(landmarks: list[TrunkLandmark], side: str) -> list[GroundRecord]:
    """The local grounds of a side's trunk landmarks (trunks without a ground have none)."""
    return [GroundRecord(lm.id, side, _t3(lm.ground.point), _t3(lm.ground.normal), float(lm.ground.offset),
                         float(lm.ground.rmse_m), int(lm.ground.inliers)) for lm in landmarks if lm.ground is not None]


GROUND_KINDS = ("local", "wide", "none")  # LocalGround.kind in a ground fitter's answer


def trunk_grounds_to_msg(grounds: list[TrunkGround], side: str, frame_id: str, stamp: float):
    """LocalGroundArray with one LocalGround per trunk landmark (the ground fitter's answer): its plane (the
    local ground, else the wide one, else none) and what the trunk's cylinder fit reads. float64 fields only:
    trunk_grounds_from_msg gives the same values back, bit for bit."""
    from orchard_mapping_msgs.msg import LocalGround, LocalGroundArray

    out = LocalGroundArray()
    stamp_header(out.header, stamp, frame_id)
    for g in grounds:
        m = LocalGround()
        m.header = out.header
        m.tree_id, m.side = int(g.id), side
        plane = g.ground if g.ground is not None else g.wide_ground
        m.kind = "local" if g.ground is not None else "wide" if g.wide_ground is not None else "none"
        if plane is not None:
            m.point.x, m.point.y, m.point.z = _t3(plane.point)
            m.normal.x, m.normal.y, m.normal.z = _t3(plane.normal)
            m.offset, m.fit_rmse = float(plane.offset), float(plane.rmse_m)
            m.inlier_count, m.candidate_count = int(plane.inliers), int(plane.candidates)
            m.support_area, m.support_offset = float(plane.support_m2), float(plane.support_offset_m)
            if plane.ground_cells is not None:
                m.ground_cells = array.array("d", np.asarray(plane.ground_cells, np.float64).tobytes())
        else:
            m.offset = m.fit_rmse = m.support_area = m.support_offset = math.nan
        c = g.coarse
        m.axis_point.x, m.axis_point.y, m.axis_point.z = _t3(c.origin)
        m.axis.x, m.axis.y, m.axis.z = _t3(c.axis)
        m.axis_radius, m.trunk_bottom, m.trunk_top = float(c.radius), float(g.bottom_m), float(g.top_m)
        m.view_indices = [int(v) for v, _ in g.detections]
        m.detection_indices = [int(d) for _, d in g.detections]
        m.point_indices = array.array("I", np.asarray(g.point_indices, np.uint32).tobytes())  # whole, not per item
        out.grounds.append(m)
    return out


def trunk_grounds_from_msg(msg) -> tuple[str, float, list[TrunkGround]]:
    """(frame id, stamp s, the trunk landmarks' grounds) of a ground fitter's LocalGroundArray
    (trunk_grounds_to_msg); GroundMessageError for one that is not."""
    out = []
    for m in msg.grounds:
        where = f"local ground of trunk {m.tree_id} ({m.side})"
        if m.kind not in GROUND_KINDS:
            raise GroundMessageError(f"{where}: kind {m.kind!r} is not one of {GROUND_KINDS}: not a ground "
                                     "fitter's answer")
        if len(m.view_indices) != len(m.detection_indices) or len(m.ground_cells) % 3:
            raise GroundMessageError(f"{where}: {len(m.view_indices)} view indices for {len(m.detection_indices)} "
                                     f"detections, {len(m.ground_cells)} ground cell values (x y z each)")
        plane = None
        if m.kind != "none":
            plane = LocalGroundFit(normal=np.array([m.normal.x, m.normal.y, m.normal.z]), offset=float(m.offset),
                                   point=np.array([m.point.x, m.point.y, m.point.z]), inliers=int(m.inlier_count),
                                   rmse_m=float(m.fit_rmse), candidates=int(m.candidate_count),
                                   support_m2=float(m.support_area), support_offset_m=float(m.support_offset),
                                   ground_cells=np.asarray(m.ground_cells, np.float64).reshape(-1, 3))
        coarse = Cylinder(np.array([m.axis.x, m.axis.y, m.axis.z]),
                          np.array([m.axis_point.x, m.axis_point.y, m.axis_point.z]), float(m.axis_radius))
        out.append(TrunkGround(int(m.tree_id), tuple(zip((int(v) for v in m.view_indices),
                                                         (int(d) for d in m.detection_indices), strict=True)),
                               np.asarray(m.point_indices, np.int64), coarse, float(m.trunk_bottom), float(m.trunk_top),
                               plane if m.kind == "local" else None, plane if m.kind == "wide" else None))
    return msg.header.frame_id, msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, out


def _nan(v: float | None) -> float:
    return math.nan if v is None else float(v)


def _none(v: float) -> float | None:
    return None if math.isnan(v) else float(v)


def trees_to_msg(trees: list[ResultTree], frame_id: str, stamp: float):
    """TreeTraitsArray of result trees (frame map): a trait not measured is NaN (counts -1), as the message says.
    Every value of trees.json travels except fruit positions and extra keys (the fruit counted from each side
    travel)."""
    from orchard_mapping_msgs.msg import TreeTraits, TreeTraitsArray

    out = TreeTraitsArray()
    stamp_header(out.header, stamp, frame_id)
    for t in trees:
        m = TreeTraits()
        m.header = out.header
        m.tree_id = int(t.id)
        m.position.x, m.position.y, m.position.z = (float(v) for v in t.position)
        m.trunk_diameter, m.height, m.canopy_volume = (_nan(t.trunk_diameter_m), _nan(t.height_m),
                                                       _nan(t.canopy_volume_m3))
        m.fruit_count = -1 if t.fruit_count is None else int(t.fruit_count)
        for side in ("front", "back"):
            n = t.extra.get(f"fruit_count_{side}")
            setattr(m, f"fruit_count_{side}", -1 if n is None else int(n))
        per = t.per_side or {}
        for side in ("front", "back"):
            own = per.get(side) or {}
            setattr(m, f"trunk_id_{side}", int(own["trunk_id"]) if own.get("trunk_id") is not None else -1)
            setattr(m, f"trunk_diameter_{side}", _nan(own.get("diameter_m")))
        m.flags = list(t.flags)
        out.trees.append(m)
    return out


def trees_from_msg(msg) -> tuple[str, float, list[ResultTree]]:
    """(frame id, stamp s, trees) of a TreeTraitsArray: the result trees trees_to_msg sent."""
    trees = []
    for m in msg.trees:
        per = {side: {"trunk_id": int(getattr(m, f"trunk_id_{side}")),
                      "diameter_m": _none(getattr(m, f"trunk_diameter_{side}"))}
               for side in ("front", "back") if getattr(m, f"trunk_id_{side}") >= 0}
        trees.append(ResultTree(int(m.tree_id), (float(m.position.x), float(m.position.y), float(m.position.z)),
                                _none(m.trunk_diameter), _none(m.height), _none(m.canopy_volume),
                                None if m.fruit_count < 0 else int(m.fruit_count), per_side=per or None,
                                flags=tuple(str(f) for f in m.flags),
                                extra={f"fruit_count_{side}": int(getattr(m, f"fruit_count_{side}"))
                                       for side in ("front", "back") if getattr(m, f"fruit_count_{side}") >= 0}))
    return msg.header.frame_id, msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec, trees
