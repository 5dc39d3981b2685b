"""Fruit in 3D (paper: "Fruit Counting" / yield mapping): each side's fruit from its keyframes' fruit instances
and depth, then both sides' fruit in the merged map, each fruit once.

1. Observation (one keyframe, one fruit instance of the image segmentation, core.fruit_pixels): the instance's
   pixels with depth (RGB-D: a pixel is a point). The fruit's centre lies one radius behind its nearest visible
   surface along the ray through the instance's centre; its radius is the instance's enclosing circle (a leaf
   that hides part of a fruit leaves its outline: the area underestimates it) at that depth.
2. Per side: the observations of the same fruit in neighbouring keyframes lie within a fraction of a radius of
   each other in the side's frame, two touching fruit one diameter apart: single-linkage components within
   `link_factor` x the smaller radius are one fruit each. Position and diameter: medians over its views. A
   fruit seen in fewer than `min_views` keyframes is dropped (a glimpse or a red leaf); a view far larger than
   the side's typical fruit (one outline round two touching fruit) is left out and the fruit linked again; a
   fruit far smaller (a piece seen between leaves, a red speck) is dropped.
3. Both sides (after the merge, in map): the back side's fruit are shifted by the offset their neighbourhood's
   candidate pairs agree on (what the merge and the sides' drift left between the sides); then a front and a
   back fruit are one fruit when their centres lie within
   `match_factor` x their mean radius; one-to-one, nearest first (scipy's linear_sum_assignment on the gated
   distances). The paper's inclusion-exclusion count (front + back - fruit of one side with any fruit of the
   other within the gate) is kept as the baseline it is measured against.

Frames: odom_<side> for a side's fruit, map after the merge; metres.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import OrchardMappingError

__all__ = [
    "FruitError",
    "FruitParams",
    "FruitObservation",
    "SideFruit",
    "RowFruit",
    "fruit_observations",
    "fruit_of_side",
    "associate_sides",
    "inclusion_exclusion_count",
]


class FruitError(OrchardMappingError, ValueError):
    """Fruit input that cannot be used (names what is wrong: which array, which shape)."""


# A sphere seen whole: the median depth over its disc lies r / sqrt(2) in front of its centre (half the disc's
# area lies within rho^2 < r^2 / 2). Leaves hiding part of it move this by less than that.
SURFACE_DEPTH_OF_RADIUS = float(np.sqrt(0.5))
MIN_INNER_PIXELS = 10  # fewer pixels inside the outline: the outline's own depths are used


@dataclass(frozen=True)
class FruitParams:
    """config `fruit` section: where fruit are looked for, and how they are placed, linked and matched."""

    enabled: bool = False  # off: no fruit stage (fruit_count stays empty)
    # model: the pixel model below | masks: fruit instances of masks_dir/<side>/ (the simulator's, or a user's
    # annotations: measures the 3D stage alone)
    source: Literal["model", "masks"] = "model"
    masks_dir: str = ""
    # the pixel model (core.fruit_pixels; a relative path is looked up from the working directory, then
    # beside the package)
    model: str = "models/fruit_net.onnx"
    # m of camera path between the keyframes searched for fruit: the trunk detector's spacing (a fruit is in
    # view for ~1.5 m of path at 1.4 m range: about ten looks)
    every_m: float = 0.15

    min_pixels: int = 20  # px with depth an instance needs (the simulator's visibility rule: 20 px)
    min_radius_m: float = 0.015  # an instance smaller than this at its depth is no fruit (a berry, a bud)
    max_radius_m: float = 0.08  # or larger (a red cluster of leaves, two fruit merged in one instance)
    # observations within this x the smaller radius are the same fruit (two touching fruit: 2.0). 10-tree standard
    # row, the simulator's masks and poses: 0.5 split 20 of 290 fruit in two, 1.0 none
    link_factor: float = 1.0
    # keyframes (0.15 m apart) a fruit is seen in: 1 let 38 fruit be counted twice (a glimpse beside its main
    # cluster), 2 six, 3 none, and lost none of the fruit the truth calls visible
    min_views: int = 3
    best_views: int = 3  # its position and size: medians over this many views showing most of its pixels
    match_factor: float = 1.0  # a front and a back fruit are one within this x their mean radius
    # Before they are matched, the back side's fruit are shifted by the offset their neighbourhood's fruit agree
    # on (`fruit_offsets`): the merge and each side's drift leave the sides some centimetres apart where the
    # trunks were few or the path wandered (hand-held rows of the second renderer: 5-15 cm, twice the gate), and
    # the fruit both sides saw then never match. Candidate pairs within align_gate_m (0: off), the back fruit
    # within align_radius_m of each one, the offset most pairs agree on within align_kernel_m, taken where at
    # least align_min_support pairs agree. The kernel: each side places a fruit 1-1.5 cm off (the simulator's rows),
    # so two pairs of the same shift differ by up to ~4 cm; pairs of unrelated fruit agree by chance under once
    # a fruit.
    align_gate_m: float = 0.25
    align_radius_m: float = 0.6
    align_kernel_m: float = 0.04
    align_min_support: int = 5
    # a side's fruit smaller than this x the median diameter of its well-seen fruit (seen in at least the median
    # number of keyframes) are dropped (0: none). The pixel model's false fruit are mostly pieces of fruit
    # seen between leaves and red specks, median 50 mm across against 82 mm. Chosen on the 10-tree standard
    # row of seed 21 with the shipped pixel model (FruitUNet): 0 / 0.5 / 0.6 / 0.7 gave row counts +14.2 / +2.1 /
    # -5.3 / -13.5 % of the fruit visible, per-tree count errors 13.9 / 7.9 / 6.5 / 13.2 % (median), counted twice
    # 17.5 / 8.2 / 4.4 / 2.2 per 100 seen from both (the earlier, smaller network: +61 / +24 at 0.6 / +5.0 at 0.7)
    min_size_of_median: float = 0.6
    # a view whose instance is larger than this x the same typical diameter is left out (0: none), and the fruit
    # linked again without it: the pixel model's instance of two touching fruit (one outline round both)
    # places a "fruit" between them, twice as large, which chains both into one fruit and becomes its largest,
    # so "best", view. 10-tree standard row of seed 21, pixel model, the side's fruit against the truth
    # (diameter MAE front / back): off 13.1 / 11.6 mm, 1.6: 10.5 / 8.3, 1.4: 7.9 / 6.4, 1.3: 6.5 / 6.0, 1.2:
    # 5.7 / 6.1 (and 8 more false fruit on the back), true fruit found 176-177 / 164-167 each time. 1.3 and not
    # lower: a real block's fruit vary more than the simulator's (71-89 mm, 5-95 %), and a large fruit's whole
    # views must stay
    max_size_of_median: float = 1.3
    ground_margin_m: float = 0.10  # a fruit whose bottom is less than this above the local ground lies on it

    def __post_init__(self) -> None:
        for name in ("min_radius_m", "max_radius_m", "link_factor", "match_factor", "every_m", "align_radius_m",
                     "align_kernel_m", "align_min_support"):
            if not getattr(self, name) > 0:
                raise FruitError(f"fruit.{name} must be > 0, got {getattr(self, name)!r}")
        if not self.align_gate_m >= 0:
            raise FruitError(f"fruit.align_gate_m must be >= 0 (0: off), got {self.align_gate_m!r}")
        if not self.max_radius_m > self.min_radius_m:
            raise FruitError(f"fruit.max_radius_m ({self.max_radius_m}) must exceed min_radius_m ({self.min_radius_m})")
        if self.enabled and self.source == "masks" and not self.masks_dir:
            raise FruitError("fruit.source is 'masks' but fruit.masks_dir is empty")
        if not 0.0 <= self.min_size_of_median < 1.0:
            raise FruitError(f"fruit.min_size_of_median must be in [0, 1), got {self.min_size_of_median!r}")
        if not (self.max_size_of_median == 0.0 or self.max_size_of_median > 1.0):
            raise FruitError(f"fruit.max_size_of_median must be 0 (off) or > 1, got {self.max_size_of_median!r}")
        if self.min_views < 1 or self.min_pixels < 1:
            raise FruitError(f"fruit.min_views and fruit.min_pixels must be >= 1, got {self.min_views}, "
                             f"{self.min_pixels}")


@dataclass(frozen=True)
class FruitObservation:
    """One fruit instance of one keyframe, placed in the side's frame."""

    keyframe: int  # keyframe index in the side
    centre: np.ndarray  # (3,) m, odom_<side>
    radius_m: float
    pixels: int  # instance pixels with depth
    instance: int = 0  # its instance id in the keyframe's segmentation


@dataclass(frozen=True)
class SideFruit:
    """One side's fruit: one row per fruit."""

    side: str
    positions: np.ndarray  # (F, 3) m, odom_<side> (map once moved)
    diameters_m: np.ndarray  # (F,)
    views: np.ndarray  # (F,) int, keyframes each was seen in


@dataclass(frozen=True)
class RowFruit:
    """Both sides' fruit, each fruit once, in map."""

    positions: np.ndarray  # (F, 3) m, map
    diameters_m: np.ndarray  # (F,)
    seen_from: np.ndarray  # (F,) str: "front", "back" or "both"
    front_index: np.ndarray  # (F,) int, the front side's fruit row, -1 none
    back_index: np.ndarray  # (F,) int


def _check_image(a: np.ndarray, what: str, shape: tuple[int, int] | None = None) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 2 or (shape is not None and a.shape != shape):
        raise FruitError(f"{what} must be (H, W){'' if shape is None else f' = {shape}'}, got {a.shape}")
    return a


def _enclosing_cone(u: np.ndarray, v: np.ndarray, intr: CameraIntrinsics) -> tuple[np.ndarray, float]:
    """The axis (3,) unit, camera frame, and sin(half angle) of the narrowest cone through the camera holding the
    pixels' rays: a sphere's silhouette is a circle only seen along its centre's ray (off the image centre it
    is an ellipse, and the enclosing circle in pixels overstates its size by up to ~5 %), so the rays are
    projected on the plane normal to a first axis (the pixel enclosing circle's centre) and the circle found
    there."""
    (cu, cv), _ = cv2.minEnclosingCircle(np.column_stack([u, v]).astype(np.float32))
    a = np.array([(cu - intr.cx) / intr.fx, (cv - intr.cy) / intr.fy, 1.0])
    a /= np.linalg.norm(a)
    rays = np.column_stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones(len(u))])  # (P, 3)
    # a frame with a as its z axis
    x = np.cross([0.0, 1.0, 0.0], a)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(a, x), a])  # rows
    q = rays @ R.T  # (P, 3)
    t = q[:, :2] / q[:, 2:3]  # (P, 2) tangent-plane coordinates
    scale = 0.5 * (intr.fx + intr.fy)  # in pixel-like units for the float32 circle fit
    (tx, ty), rho = cv2.minEnclosingCircle((t * scale).astype(np.float32))
    axis = R.T @ np.array([tx / scale, ty / scale, 1.0])
    axis /= np.linalg.norm(axis)
    tan_a = (rho + 0.5) / scale  # the outline's pixel centres lie half a pixel inside the silhouette
    return axis, float(tan_a / np.sqrt(1.0 + tan_a * tan_a))


def fruit_observations(instances: np.ndarray, depth: np.ndarray, T_odom_cam: np.ndarray, intr: CameraIntrinsics,
                       params: FruitParams, keyframe: int = 0) -> list[FruitObservation]:
    """The fruit instances (H, W) int (0 none, k > 0 instance k) of one keyframe with its depth (H, W) m (0 =
    none) and pose T_odom_cam (4, 4): one observation per instance with enough depth pixels, in odom."""
    inst = _check_image(instances, "fruit instances")
    z = _check_image(depth, "depth", inst.shape).astype(np.float64)
    T = np.asarray(T_odom_cam, float)
    if T.shape != (4, 4):
        raise FruitError(f"T_odom_cam must be (4, 4), got {T.shape}")
    valid = (inst > 0) & np.isfinite(z) & (z > 0)
    if not valid.any():
        return []
    # an instance's outline pixels: a depth camera mixes their depth with what lies behind or in front (flying
    # pixels), so the depth is read inside the outline
    lab = inst.astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    inner = (cv2.erode(lab, kernel) == lab) & (cv2.dilate(lab, kernel) == lab)
    v, u = np.nonzero(valid)  # (P,), (P,)
    ids = inst[v, u]
    order = np.argsort(ids, kind="stable")
    v, u, ids, zz = v[order], u[order], ids[order], z[v[order], u[order]]
    inside = inner[v, u]
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    ends = np.r_[starts[1:], len(ids)]
    out = []
    for s, e in zip(starts.tolist(), ends.tolist(), strict=True):
        if e - s < params.min_pixels:
            continue
        uu, vv, dz, ins = u[s:e], v[s:e], zz[s:e], inside[s:e]
        if uu.min() == 0 or vv.min() == 0 or uu.max() == inst.shape[1] - 1 or vv.max() == inst.shape[0] - 1:
            continue  # cut by the image border: its outline says nothing of its size or centre
        direction, sin_a = _enclosing_cone(uu, vv, intr)
        use = ins if ins.sum() >= MIN_INNER_PIXELS else np.ones(len(uu), bool)
        rays = np.column_stack([(uu[use] - intr.cx) / intr.fx, (vv[use] - intr.cy) / intr.fy, np.ones(use.sum())])
        rng_s = float(np.median((dz[use, None] * rays) @ direction))  # m, the visible surface along the axis
        # the visible surface lies on average SURFACE_DEPTH_OF_RADIUS r in front of the centre, and the cone
        # that just holds the fruit's outline has sin(half angle) = r / (distance to the centre):
        # r = (rng_s + k r) sin_a, solved for r
        r = rng_s * sin_a / max(1.0 - SURFACE_DEPTH_OF_RADIUS * sin_a, 1e-6)
        if not params.min_radius_m <= r <= params.max_radius_m:
            continue
        p_cam = direction * (rng_s + SURFACE_DEPTH_OF_RADIUS * r)
        out.append(FruitObservation(keyframe, T[:3, :3] @ p_cam + T[:3, 3], float(r), e - s, int(ids[s])))
    return out


def _linked(observations: list[FruitObservation], params: FruitParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Observations linked within link_factor x the smaller radius (single linkage), kept when seen in min_views
    keyframes: per fruit its position (F, 3), diameter (F,) and number of keyframes (F,), medians over the
    best_views views that show most of its pixels."""
    c = np.array([o.centre for o in observations]).reshape(-1, 3)  # (O, 3)
    r = np.array([o.radius_m for o in observations])  # (O,)
    kf = np.array([o.keyframe for o in observations], int)
    n = len(c)
    pairs = cKDTree(c).query_pairs(params.link_factor * float(r.max()), output_type="ndarray") if n else \
        np.zeros((0, 2), int)  # (Q, 2)
    if len(pairs):
        d = np.linalg.norm(c[pairs[:, 0]] - c[pairs[:, 1]], axis=1)
        pairs = pairs[d <= params.link_factor * np.minimum(r[pairs[:, 0]], r[pairs[:, 1]])]
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n)) if len(pairs) else \
        coo_matrix((n, n))
    k, label = connected_components(graph, directed=False)
    px = np.array([o.pixels for o in observations])
    pos, dia, views = [], [], []
    for j in range(k):
        m = np.flatnonzero(label == j)
        nv = len(np.unique(kf[m]))
        if nv < params.min_views:
            continue
        # the views that show most of the fruit (the paper's "three frames where it shows most pixels"): a view
        # where leaves hide part of it puts its centre and outline off
        best = m[np.argsort(-px[m], kind="stable")[: params.best_views]]
        pos.append(np.median(c[best], axis=0))
        dia.append(2.0 * float(np.median(r[best])))
        views.append(nv)
    return np.array(pos).reshape(-1, 3), np.array(dia), np.array(views, int)


def _typical_diameter(diameters: np.ndarray, views: np.ndarray) -> float:
    """m: the median diameter of the fruit seen in at least the median number of keyframes (pieces of fruit
    and specks seldom are; one variety's fruit are of a size)."""
    return float(np.median(diameters[views >= np.median(views)]))


def fruit_of_side(side: str, observations: list[FruitObservation], params: FruitParams) -> SideFruit:
    """The side's fruit: observations linked within link_factor x the smaller radius (single linkage), kept
    when seen in min_views keyframes; views far larger than the side's typical fruit left out
    (max_size_of_median) and fruit far smaller dropped (min_size_of_median); medians of position and diameter."""
    empty = SideFruit(side, np.zeros((0, 3)), np.zeros(0), np.zeros(0, int))
    if not observations:
        return empty
    pos_a, dia_a, views_a = _linked(observations, params)
    if len(pos_a) and params.max_size_of_median > 0:
        # an instance round two touching fruit (or a fruit and a red leaf beside it): left out, and the fruit
        # linked again, so that it neither chains two fruit into one nor stands as a fruit's best view
        limit = params.max_size_of_median * _typical_diameter(dia_a, views_a)
        whole = [o for o in observations if 2.0 * o.radius_m <= limit]
        if len(whole) < len(observations):
            pos_a, dia_a, views_a = _linked(whole, params)
    if not len(pos_a):
        return empty
    if params.min_size_of_median > 0:
        # a "fruit" far smaller than the side's typical one is a piece of a fruit seen between leaves or a red
        # speck the pixel model took for one
        keep = dia_a >= params.min_size_of_median * _typical_diameter(dia_a, views_a)
        pos_a, dia_a, views_a = pos_a[keep], dia_a[keep], views_a[keep]
    return SideFruit(side, pos_a, dia_a, views_a)


def _gated_pairs(a: SideFruit, b: SideFruit, factor: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distances (A, B) and the gate (A, B): within factor x the pair's mean radius."""
    d = np.linalg.norm(a.positions[:, None, :] - b.positions[None, :, :], axis=2)
    gate = factor * 0.25 * (a.diameters_m[:, None] + b.diameters_m[None, :])
    return d, gate, d <= gate


def fruit_offsets(front: SideFruit, back: SideFruit, params: FruitParams) -> np.ndarray:
    """(B, 3) m: the shift that brings each back fruit's neighbourhood onto the front side's fruit (zero where
    fewer than align_min_support candidate pairs agree).

    Candidate pairs: a front and a back fruit within align_gate_m. For back fruit k, the pairs whose back fruit
    lies within align_radius_m of it vote: the pair whose difference (front - back) has most others within
    align_kernel_m wins, and the offset is the mean difference of those, taken when they are at least
    align_min_support and twice the pairs that agree on no shift. Fruit hang in irregular constellations, so
    only the true shift gathers many pairs."""
    off = np.zeros((len(back.positions), 3))
    if params.align_gate_m <= 0 or not len(front.positions) or not len(back.positions):
        return off
    d = np.linalg.norm(front.positions[:, None, :] - back.positions[None, :, :], axis=2)  # (F, B)
    fi, bi = np.nonzero(d <= params.align_gate_m)  # (P,) candidate pairs
    if len(fi) < params.align_min_support:
        return off
    v = front.positions[fi] - back.positions[bi]  # (P, 3) front - back
    voters = cKDTree(back.positions[bi]).query_ball_point(back.positions, params.align_radius_m)  # per back fruit
    for k, idx in enumerate(voters):
        if len(idx) < params.align_min_support:
            continue
        vk = v[idx]  # (n, 3)
        agree = np.linalg.norm(vk[:, None, :] - vk[None, :, :], axis=2) <= params.align_kernel_m  # (n, n)
        support = agree.sum(axis=1)
        best = int(np.argmax(support))
        # a shift only where it gathers twice the pairs that no shift does: fruit hanging in a regular pattern
        # (or a side already in place) agree at the pattern's spacing too, and must not be moved by it
        unshifted = int((np.linalg.norm(vk, axis=1) <= params.align_kernel_m).sum())
        if support[best] >= max(params.align_min_support, 2 * unshifted):
            off[k] = vk[agree[best]].mean(axis=0)
    return off


def associate_sides(front: SideFruit, back: SideFruit, params: FruitParams) -> RowFruit:
    """Both sides' fruit (in map) as one list, each fruit once: the back side's fruit shifted onto the front's
    (`fruit_offsets`), then gated one-to-one assignment, nearest first."""
    for _ in range(2):  # a second pass takes up what a turn of the side left within each neighbourhood
        back = dataclasses.replace(back, positions=back.positions + fruit_offsets(front, back, params))
    nf, nb = len(front.positions), len(back.positions)
    fi, bi = np.zeros(0, int), np.zeros(0, int)
    if nf and nb:
        d, _, ok = _gated_pairs(front, back, params.match_factor)
        if ok.any():
            cost = np.where(ok, d, 1e6)
            fi, bi = linear_sum_assignment(cost)
            keep = ok[fi, bi]
            fi, bi = fi[keep], bi[keep]
    f_only = np.setdiff1d(np.arange(nf), fi)
    b_only = np.setdiff1d(np.arange(nb), bi)
    pos = np.concatenate([0.5 * (front.positions[fi] + back.positions[bi]), front.positions[f_only],
                          back.positions[b_only]]).reshape(-1, 3)
    dia = np.concatenate([0.5 * (front.diameters_m[fi] + back.diameters_m[bi]), front.diameters_m[f_only],
                          back.diameters_m[b_only]])
    seen = np.array(["both"] * len(fi) + ["front"] * len(f_only) + ["back"] * len(b_only), dtype=object)
    f_idx = np.concatenate([fi, f_only, np.full(len(b_only), -1)]).astype(int)
    b_idx = np.concatenate([bi, np.full(len(f_only), -1), b_only]).astype(int)
    return RowFruit(pos, dia, seen, f_idx, b_idx)


def inclusion_exclusion_count(front: SideFruit, back: SideFruit, params: FruitParams) -> int:
    """The paper's baseline: front + back - the front fruit that have any back fruit within the gate."""
    if not len(front.positions) or not len(back.positions):
        return len(front.positions) + len(back.positions)
    _, _, ok = _gated_pairs(front, back, params.match_factor)
    return len(front.positions) + len(back.positions) - int(ok.any(axis=1).sum())
