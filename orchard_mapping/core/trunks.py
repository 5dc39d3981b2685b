"""Trunk landmarks of one side (paper: "Trunk Cylinder Modeling", "Local Ground Plane").

From one side's reconstruction (keyframe poses, fused cloud, depth of
keyframes spaced along the path: raw, or cleaned by fusion) and the trunk detections of those keyframes:

1. Association: every detected trunk instance is placed in the side's frame
   by the median of its depth pixels; instances whose places lie within
   `associate_radius_m` of each other across the row direction form one trunk
   landmark (one tree, one side).
2. Segmentation: a fused point belongs to the trunk when it projects into the
   mask of one of the landmark's detections and is not hidden in that frame
   (the union of trunk masks over nearby frames, as the paper does).
3. A coarse cylinder over the whole trunk gives the axis (RANSAC, 3D only).
4. The local ground under the tree: RANSAC with the trunk axis as the prior
   (`core/ground.py`).
5. The trunk segment around the diameter height (`diameter_height_m` above
   the local ground, `band_m` long) is fitted with eq. objectCylinder
   (3D term plus the 2D terms of every detection that sees the band); its
   diameter is the trunk diameter. The 3D-only fit is the baseline.

Two steps, each with one implementation: `fit_side_grounds` does 1-4 (a `TrunkGround` per landmark: its
detections, points, coarse axis and grounds), `fit_trunk_cylinders` does 5 against those grounds.
`orchard-map run` calls both in one process (`build_trunk_landmarks`); the live graph fits the grounds in
the local_ground_fitter node and the cylinders in the odometry node's side finish. Each landmark's fits
draw from random streams of their own (the seed, the step, the landmark), so the split draws the same.

A trunk whose band has too few points or views is reported hidden at the
diameter height (flag), with no diameter: never a made-up cylinder.
Frames: everything in odom_<side> (metres) unless a name says `_cam`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from orchard_mapping.core.cylinder import (
    Cylinder,
    CylinderError,
    CylinderFit,
    CylinderView,
    fit_cylinder,
    point_distance,
    refine_cone_axis,
)
from orchard_mapping.core.detection import CLASS_TRUNK, Detection
from orchard_mapping.core.geometry import SlabIndex, group_medians, transform_points
from orchard_mapping.core.ground import GroundParams, LocalGroundFit, fit_local_ground, ground_neighbourhood
from orchard_mapping.core.odometry import backproject
from orchard_mapping.core.types import CameraIntrinsics, ImagePatch, mask_bounds
from orchard_mapping.errors import OrchardMappingError

__all__ = [
    "TrunkError",
    "TrunkGround",
    "TrunkLandmark",
    "TrunkObservation",
    "TrunkParams",
    "TrunkView",
    "build_trunk_landmarks",
    "fit_side_grounds",
    "fit_trunk_cylinders",
    "ground_around_trunk",
    "side_up_direction",
]


class TrunkError(OrchardMappingError, ValueError):
    """Trunk landmarks cannot be built from the given data."""


@dataclass(frozen=True)
class TrunkParams:
    """Settings of trunk modelling (config section `trunks`)."""

    __pydantic_config__ = {"extra": "forbid"}  # config files: unknown keys are errors

    # Where trunk masks come from: "model" (the ONNX detector at `model`), "masks" (instance masks on disk
    # under `masks_dir`/<side>/: the simulator's, or a user's annotations; measures the geometry alone),
    # or "off" (no trunks, no local grounds).
    source: str = "model"
    model: str = "models/trunk_maskrcnn.onnx"  # relative paths: to the working directory, then the package
    masks_dir: str = ""
    score_threshold: float = 0.5  # detections scored lower are dropped
    mask_threshold: float = 0.5  # mask probability of a trunk pixel
    max_mask_overlap: float = 0.5  # a mask more than this fraction inside higher-scored ones is a duplicate
    # The detector also sees each frame mirrored (test-time flip): more trunks found on scenes unlike the
    # training ones, at twice the detector's time; off for live use (models/README.md).
    flip_test: bool = False
    # Trunks from geometry (core.geometric_trunks: vertical round columns of the fused cloud): "off" (the
    # detector alone), "fill" (the detector, plus each column on the row line that it missed, modelled from
    # the depth pixels on the column's cylinder), or "only" (geometry alone, no detector trunks; its posts stay).
    geometric: str = "fill"
    input_width: int = 0  # px, the model's input size (0: the model's own, or the frame's if dynamic)
    input_height: int = 0
    threads: int = 2  # onnxruntime intra-op threads
    detect_every_m: float = 0.15  # m of camera path between frames given to the detector
    diameter_height_m: float = 0.30  # m above the local ground: where the diameter is read (horticulture's habit)
    band_m: float = 0.16  # m, length of the trunk segment fitted around the diameter height
    associate_radius_m: float = 0.25  # m, detections closer than this across the row are one trunk
    # Detections a trunk landmark needs. Frames are detect_every_m apart, so a trunk in view over a metre
    # of path has ~7: on the 10-tree rows every true trunk had 6 or more; the one landmark made up from
    # a glimpse (demo row, back side, a 35 mm "trunk" beside a real one) had 2.
    min_observations: int = 3
    min_mask_pixels: int = 150  # smaller masks (far or clipped trunks) are not used
    visibility_tol_m: float = 0.03  # m, a fused point is hidden in a frame when that frame saw depth this much closer
    max_axis_angle_deg: float = 30.0  # deg, trunk axis vs the side's up direction (lean + camera roll)
    radius_min_m: float = 0.01  # m
    radius_max_m: float = 0.25  # m
    ransac_threshold_m: float = 0.008  # m, point-to-surface distance of a RANSAC inlier
    ransac_iterations: int = 300
    min_band_points: int = 60  # fused points a band fit needs, else the trunk is hidden at the diameter height
    use_2d: bool = True  # eq. objectCylinder's 2D term (False: the 3D-only baseline)
    sigma_3d_m: float = 0.003  # m, fused point noise (3D term's scale)
    sigma_px: float = 1.0  # px, 2D term's scale
    lam: float = 1.0  # lambda of eq. objectCylinder
    huber_k: float = 1.345  # Huber threshold in sigmas
    # px: a mask edge is moved to the trunk's depth edge within this reach (0: mask edges as they are).
    # A learned mask's edges stray +-2-3 px (10-90 %, up to 7 px) from the trunk's; on the 10-tree
    # standard and slope_weeds rows with the shipped model, 6 px took the 2D fit's diameter MAE from
    # 3.24/1.92/2.46/1.63 to 1.42/1.00/0.76/1.08 mm (front/back sides); on exact masks it changes < 0.1 mm.
    edge_snap_px: int = 6
    # Depth the 2D terms (and the merge's cone axis) read in each detector frame: "raw" (the sensor's, up to
    # fusion.depth_max_m) or "cleaned" (the paper's: checked against the fused surface ray cast into the frame,
    # floating pixels removed). Measured with the shipped detector on 10-tree rows (standard seed 0,
    # slope_weeds seeds 0-2; benchmarks/trunks.py, docs/performance.md): diameter MAE over the 8 sides 1.22
    # (raw) vs 1.23 mm (cleaned), every side within 0.4 mm of the other; the Huber loss and the edge snap
    # already set aside what the cleaning removes. Cleaning was ~4 s of fusion per side.
    view_depth: str = "raw"

    def __post_init__(self) -> None:
        if self.source not in ("model", "masks", "off"):
            raise TrunkError(f"trunks.source must be 'model', 'masks' or 'off', got {self.source!r}")
        if self.source == "masks" and not self.masks_dir:
            raise TrunkError("trunks.source is 'masks' but trunks.masks_dir is empty")
        for name in ("score_threshold", "mask_threshold", "max_mask_overlap"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise TrunkError(f"trunks.{name} must be in [0, 1], got {getattr(self, name)!r}")
        if self.geometric not in ("off", "fill", "only"):
            raise TrunkError(f"trunks.geometric must be 'off', 'fill' or 'only', got {self.geometric!r}")
        if self.view_depth not in ("raw", "cleaned"):
            raise TrunkError(f"trunks.view_depth must be 'raw' or 'cleaned', got {self.view_depth!r}")
        if self.edge_snap_px < 0:
            raise TrunkError(f"trunks.edge_snap_px must be >= 0, got {self.edge_snap_px!r}")
        if self.input_width < 0 or self.input_height < 0 or self.threads < 1:
            raise TrunkError("trunks.input_width/input_height must be >= 0 and trunks.threads >= 1")
        for name in ("detect_every_m", "diameter_height_m", "band_m", "associate_radius_m", "visibility_tol_m",
                     "radius_min_m", "radius_max_m", "ransac_threshold_m", "sigma_3d_m", "sigma_px", "huber_k"):
            if not getattr(self, name) > 0:
                raise TrunkError(f"trunks.{name} must be > 0, got {getattr(self, name)!r}")
        if self.radius_min_m >= self.radius_max_m:
            raise TrunkError("trunks.radius_min_m must be below trunks.radius_max_m")


@dataclass(frozen=True)
class TrunkView:
    """A keyframe given to the detector: its pose, depth (trunks.view_depth) and trunk detections."""

    keyframe: int  # keyframe id
    stamp: float  # s
    T_odom_cam: np.ndarray  # (4, 4)
    depth: np.ndarray | ImagePatch  # (H, W) float32 m, raw or cleaned, 0 = none (a patch: only around the detections)
    detections: list[Detection]


@dataclass(frozen=True)
class TrunkObservation:
    """One detection of a trunk landmark: what the semantic bundle adjustment needs of that frame."""

    keyframe: int  # keyframe id
    stamp: float  # s
    detection: Detection  # mask, box, score
    cylinder_cam: Cylinder | None  # the landmark's band cylinder in this camera's frame (None: no fit)
    band_pixels: int  # mask pixels with depth inside the diameter band


@dataclass(frozen=True)
class TrunkLandmark:
    """One tree's trunk as seen from one side."""

    id: int  # 0.. along the side
    axis: np.ndarray  # (3,) unit, up: the whole trunk's axis (coarse fit)
    base: np.ndarray  # (3,) m: where the axis meets the local ground (else the wide ground, else the lowest trunk point)
    length_m: float  # m, from base to the highest trunk point along the axis
    ground: LocalGroundFit | None
    band: CylinderFit | None  # the cylinder at the diameter height; None when hidden there
    diameter_m: float | None  # m, 2 r of `band`
    baseline_band: CylinderFit | None  # the 3D-only fit of the same band (the paper's baseline)
    n_points: int  # fused trunk points
    observations: list[TrunkObservation]
    flags: list[str] = field(default_factory=list)  # e.g. "hidden_at_diameter_height", "no_ground"
    # What the two-side diameter (eq. objectCylinderFB) refits: the band's fused points and normals (odom)
    # and its views (masks limited to the band rows; depth arrays shared with the side map). Not written out.
    band_points: np.ndarray | None = None  # (N, 3)
    band_normals: np.ndarray | None = None  # (N, 3)
    band_views: list[CylinderView] = field(default_factory=list)
    # The whole trunk's axis with its taper modelled (a cone: core.cylinder.refine_cone_axis): the cylinder
    # axis above leans away from the camera by the taper's half-angle; the two-side merge uses this one.
    merge_axis: np.ndarray | None = None  # (3,) unit, up
    taper: float = 0.0  # m of radius per m up the axis (negative: thinner upwards)
    # frames in which the detector called this object a post (core.posts.separate_trunks_from_posts gave it to
    # the trunk, which more frames called it): the other side's post views are weighed against them in the merge
    post_frames: int = 0


def side_up_direction(poses: np.ndarray) -> np.ndarray:
    """(3,) unit "up" of a side from its camera poses (K, 4, 4): the mean of the cameras' -y axes
    (optical frame: y points down in the image). A rough prior only: roll and pitch average out."""
    up = -poses[:, :3, 1].mean(axis=0)
    n = float(np.linalg.norm(up))
    if n < 1e-6:
        raise TrunkError("cannot tell up from the camera poses (their y axes cancel out)")
    return up / n


BAND_AGREEMENT_M = 0.010  # m: see _model_trunk, the foot below the band
TRUNK_SURFACE_M = 0.02  # m, points this close to a trunk's coarse cylinder are its surface, not ground
# The wide ground (a tree without a local ground: its diameter height and foot) keeps the plane refit within
# 5 cm of the RANSAC plane. The local ground's surface fit gives the plane of all the ground seen, and over
# the 1 m disk that plane's height at the trunk strays with the terrain's curvature: standard row, seed 0,
# the feet from the wide ground 28 and 41 mm high on one tree (9 and 29 mm with this refit), the merged
# trees' RMSE 11.0 mm (6.7 mm with the earlier local grounds).
WIDE_GROUND_REFIT = {"refine_surface": "plane", "refine_band_m": 0.05, "refine_iterations": 5}


def _backproject(depth: np.ndarray, mask: np.ndarray, intr: CameraIntrinsics, T_odom_cam: np.ndarray) -> np.ndarray:
    """(M, 3) odom points of the mask's pixels with depth (row-major pixel order)."""
    v, u = np.nonzero(mask & (depth > 0))
    uv = np.stack([u, v], axis=1).astype(float)
    return transform_points(T_odom_cam, backproject(uv, depth[v, u].astype(float), intr))


def associate_places(places: np.ndarray, up: np.ndarray, radius: float) -> np.ndarray:
    """(N,) cluster label of each detection place (N, 3): single linkage across the up direction (the
    connected components of the graph joining places closer than `radius`)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    flat = places - np.outer(places @ up, up)  # (N, 3) horizontal positions
    pairs = cKDTree(flat).query_pairs(radius, output_type="ndarray")  # (E, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(flat), len(flat)))
    return connected_components(graph, directed=False)[1]


def _trunks_up(det_points: list[np.ndarray], label: np.ndarray, up0: np.ndarray) -> np.ndarray:
    """(3,) unit: the mean long axis of the trunk clusters that are clearly elongated (PCA), else up0."""
    acc = np.zeros(3)
    for k in range(label.max() + 1):
        members = np.flatnonzero(label == k)
        if len(members) < 2:
            continue
        P = np.concatenate([det_points[i] for i in members])
        if len(P) < 50:
            continue
        w, V = np.linalg.eigh(np.cov((P - P.mean(axis=0)).T))  # ascending eigenvalues
        if w[2] < 16.0 * w[1]:  # not a trunk-like stick (long axis >= 4x the width in sd)
            continue
        a = V[:, 2] if V[:, 2] @ up0 > 0 else -V[:, 2]
        acc += len(P) * a
    n = float(np.linalg.norm(acc))
    return acc / n if n > 0 else up0


def _select_by_masks(points: np.ndarray, views: list[tuple[TrunkView, Detection]], intr: CameraIntrinsics,
                     tol: float) -> np.ndarray:
    """(P,) bool: points that project into a mask of `views` and are not hidden in that frame."""
    sel = np.zeros(len(points), bool)
    for v, det in views:
        T_cam_odom = np.linalg.inv(v.T_odom_cam)
        Xc = points @ T_cam_odom[:3, :3].T + T_cam_odom[:3, 3]  # (P, 3)
        z = Xc[:, 2]
        ok = z > 0.05
        u = np.full(len(points), -1)
        w = np.full(len(points), -1)
        u[ok] = np.round(intr.fx * Xc[ok, 0] / z[ok] + intr.cx).astype(int)
        w[ok] = np.round(intr.fy * Xc[ok, 1] / z[ok] + intr.cy).astype(int)
        ok &= (u >= 0) & (u < intr.width) & (w >= 0) & (w < intr.height)
        idx = np.flatnonzero(ok)
        inside = np.asarray(det.mask)[w[idx], u[idx]]
        d = np.asarray(v.depth)[w[idx], u[idx]]
        visible = (d <= 0) | (z[idx] <= d + tol)  # not behind what this frame saw at that pixel
        sel[idx[inside & visible]] = True
    return sel


# m added to a tree's reach along the row when its stretch of the cloud is cut out: up to 5 m of tree
# (canopy) on an axis tilted 15 deg off the row's normal plane
_SLAB_MARGIN_M = 1.5

# m above the ground: the merge axis is fitted above the trunk's foot
FOOT_CLEARANCE_M = 0.10

# depth pixels kept per trunk detection for the merge axis (of a few thousand in a frame; ~8 frames per trunk).
# 1000 rather than 3000: the cone fits of a 10-tree side 1.15 -> 0.36 s (standard row, front side)
_VIEW_POINTS_PER_DETECTION = 1000

# px: what a band view keeps around its mask: the silhouette terms look 8 px outside a mask and move its
# edges by up to edge_snap_px (core/cylinder.py); nothing else is read.
_VIEW_MARGIN_PX = 12


def _normals(points: np.ndarray, radius: float = 0.02, knn: int = 20) -> np.ndarray:
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius, knn))
    return np.asarray(pc.normals)


def _band_rows_mask(det_mask: np.ndarray, depth: np.ndarray, intr: CameraIntrinsics, T_odom_cam: np.ndarray,
                    ground: LocalGroundFit | None, h_lo: float, h_hi: float, axis_h0: float,
                    axis: np.ndarray) -> np.ndarray:
    """The detection mask cut to its image rows whose trunk pixels lie in the band [h_lo, h_hi] m.

    Whole rows are kept so that the mask's silhouette edges (whose pixels often have no depth)
    stay in. Heights above the ground plane, or along the axis above axis_h0 without a ground.
    """
    P = _backproject(depth, det_mask, intr, T_odom_cam)
    v, _ = np.nonzero(det_mask & (depth > 0))
    h = ground.height_of(P) if ground is not None else P @ axis - axis_h0
    out = np.zeros_like(det_mask)
    if len(v) == 0:
        return out
    rows, med = group_medians(v, h)  # median height per row
    keep = rows[(med >= h_lo) & (med <= h_hi)]
    out[keep] = det_mask[keep]
    return out


def ground_around_trunk(points: np.ndarray, o_bottom: np.ndarray, trunk: Cylinder, ground_params: GroundParams,
                        rng: np.random.Generator) -> LocalGroundFit | None:
    """The ground plane within ground_params.radius_m of the trunk axis (trunk prior, core.ground) from
    points (P, 3) odom; o_bottom (3,) the axis at the trunk's lowest point. The trunk's own surface
    (within TRUNK_SURFACE_M of the cylinder) is never ground."""
    cand = ground_neighbourhood(points, o_bottom, trunk.axis, ground_params, trunk_bottom_height=0.0)
    cand = cand[point_distance(points[cand], trunk) > TRUNK_SURFACE_M]
    return fit_local_ground(points[cand], trunk.axis, o_bottom, ground_params, rng)


def _wide_ground(points: np.ndarray, o_bottom: np.ndarray, trunk: Cylinder, ground_params: GroundParams,
                 rng: np.random.Generator) -> LocalGroundFit | None:
    """The ground over a disk of ground.wide_radius_m around the trunk (None if off or not found).

    Where weeds or leaves hide the local ground the diameter is still wanted, and its height needs only
    a rough ground: a wider disk shows more ground between the weeds. The plane is not the tree's local
    ground (the terrain within 0.5 m) and is not reported as one."""
    if ground_params.wide_radius_m <= ground_params.radius_m:
        return None
    return ground_around_trunk(points, o_bottom, trunk, replace(ground_params, radius_m=ground_params.wide_radius_m,
                                                                 **WIDE_GROUND_REFIT), rng)


@dataclass(frozen=True)
class TrunkGround:
    """The first step of modelling one trunk landmark (`fit_side_grounds`): which detections are the trunk, its
    points, the whole trunk's coarse axis and the ground under the tree. The second step, the band's cylinder
    (`fit_trunk_cylinders`), reads only this, the cloud and the views: the live graph fits the grounds in the
    local_ground_fitter node and sends them over (orchard_mapping_msgs/LocalGround, float64: exact)."""

    id: int  # the trunk landmark's id, 0.. along the side
    detections: tuple[tuple[int, int], ...]  # (index into the side's views, index into that view's detections)
    point_indices: np.ndarray  # (N,) int: the trunk's fused points (mask segmentation), indices into the cloud
    coarse: Cylinder  # the whole trunk's cylinder (3D RANSAC): the landmark's axis
    bottom_m: float  # m along coarse.axis: the trunk's lowest surface point (1st percentile of its points)
    top_m: float  # m along coarse.axis: its highest (99th percentile)
    ground: LocalGroundFit | None  # the tree's local ground
    # Without a local ground: the ground over ground.wide_radius_m, for the diameter height and the foot only
    # (not the tree's local ground, never reported as one); None with a local ground.
    wide_ground: LocalGroundFit | None = None


# The random streams of the two steps, one per trunk (numpy seeds (seed, step, trunk)): a landmark's fits do not
# depend on the other landmarks' draws, so the live graph, which fits all grounds in one node and all bands in
# another, draws what `orchard-map run` draws.
_GROUND_STREAM = 1
_BAND_STREAM = 2


def _stream(seed: int, step: int, k: int) -> np.random.Generator:
    return np.random.default_rng((int(seed), step, int(k)))


def _cloud(points: np.ndarray) -> np.ndarray:
    points = np.asarray(points, float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise TrunkError(f"the fused cloud must have shape (P, 3), got {points.shape}")
    return points


def _detection_points(v: TrunkView, det: Detection, intr: CameraIntrinsics) -> np.ndarray:
    """(M, 3) odom: the depth pixels of one detection's mask."""
    return _backproject(np.asarray(v.depth), np.asarray(det.mask), intr, v.T_odom_cam)


def build_trunk_landmarks(points: np.ndarray, poses: np.ndarray, views: list[TrunkView], intr: CameraIntrinsics,
                          params: TrunkParams, ground_params: GroundParams, seed: int) -> list[TrunkLandmark]:
    """Trunk landmarks with their local grounds from one side's fused cloud (P, 3) and detections: the two
    steps, `fit_side_grounds` then `fit_trunk_cylinders`, in this process.

    poses (K, 4, 4): the side's keyframe poses (for the up direction); views: the detector's frames.
    """
    grounds = fit_side_grounds(points, poses, views, intr, params, ground_params, seed)
    return fit_trunk_cylinders(points, views, intr, params, grounds, seed)


def fit_side_grounds(points: np.ndarray, poses: np.ndarray, views: list[TrunkView], intr: CameraIntrinsics,
                     params: TrunkParams, ground_params: GroundParams, seed: int) -> list[TrunkGround]:
    """Steps 1-4 of the module docstring for one side: the trunk landmarks (association, segmentation), each
    one's coarse axis and the ground under it, ordered along the path. points (P, 3) the fused cloud, poses
    (K, 4, 4) the keyframe poses (for the up direction), views the detector's frames."""
    points = _cloud(points)
    up = side_up_direction(np.asarray(poses, float))
    # 1. place every trunk detection
    dets: list[tuple[int, int]] = []  # (view, detection) indices
    places = []
    det_points: list[np.ndarray] = []
    for vi, v in enumerate(views):
        for di, det in enumerate(v.detections):
            if det.class_id != CLASS_TRUNK or int(det.mask.sum()) < params.min_mask_pixels:
                continue
            P = _detection_points(v, det, intr)
            if len(P) < params.min_mask_pixels // 3:
                continue
            dets.append((vi, di))
            places.append(np.median(P, axis=0))
            det_points.append(P[:: max(1, len(P) // 500)])
    if not dets:
        return []
    label = associate_places(np.asarray(places), up, params.associate_radius_m)
    # The cameras' mean up is off by the mean pitch (a raised sweep looks down 35 deg), enough to keep a
    # trunk seen from above apart from the same trunk seen level: take up from the trunks themselves
    # (the long axis of each well-seen trunk's points) and associate again.
    up = _trunks_up(det_points, label, up)
    label = associate_places(np.asarray(places), up, params.associate_radius_m)
    index = SlabIndex(points)
    reach = max(ground_params.radius_m, ground_params.wide_radius_m, params.associate_radius_m) + 0.1 + _SLAB_MARGIN_M
    # order landmarks along the path: by the first keyframe that saw them
    groups = sorted((np.flatnonzero(label == k) for k in range(label.max() + 1)),
                    key=lambda g: min(views[dets[i][0]].keyframe for i in g))
    out: list[TrunkGround] = []
    for k, members in enumerate(groups):
        if len(members) < params.min_observations:
            continue
        # the tree's stretch of the row: its neighbourhood and wide ground lie within `reach` of its centre
        # across the row, and a trunk axis tilts by at most max_axis_angle_deg over the tree's height
        slab = index.slab(np.median(np.asarray(places)[members], axis=0), reach)
        g = _trunk_ground(len(out), [dets[i] for i in members], views, np.asarray(places)[members], points, slab, up,
                          intr, params, ground_params, _stream(seed, _GROUND_STREAM, k))
        if g is not None:
            out.append(g)
    return out


def _trunk_ground(lm_id: int, members: list[tuple[int, int]], views: list[TrunkView], places: np.ndarray,
                  cloud: np.ndarray, slab: np.ndarray, up: np.ndarray, intr: CameraIntrinsics, params: TrunkParams,
                  ground_params: GroundParams, rng: np.random.Generator) -> TrunkGround | None:
    """One landmark's segmentation, coarse axis and grounds (None: too few trunk points, or no axis).
    slab: the indices of the cloud's points in the tree's stretch of the row."""
    points = cloud[slab]
    centre = np.median(places, axis=0)  # (3,)
    rel = points - centre
    radial = np.linalg.norm(rel - np.outer(rel @ up, up), axis=1)
    near = np.flatnonzero(radial < max(ground_params.radius_m, params.associate_radius_m) + 0.1)
    local = points[near]  # (L, 3) the tree's neighbourhood
    obs = [(views[vi], views[vi].detections[di]) for vi, di in members]
    trunk_sel = _select_by_masks(local, obs, intr, params.visibility_tol_m)
    trunk = local[trunk_sel]
    if len(trunk) < params.min_band_points:
        return None  # a few stray pixels: not a trunk we can model
    try:  # 3. coarse axis from the whole trunk
        coarse = fit_cylinder(trunk, _normals(trunk), [], intr, rng, up=up, threshold_m=params.ransac_threshold_m,
                              iterations=params.ransac_iterations, max_axis_angle_deg=params.max_axis_angle_deg,
                              radius_range_m=(params.radius_min_m, params.radius_max_m), use_2d=False,
                              sigma_3d_m=params.sigma_3d_m, huber_k=params.huber_k)
    except CylinderError:
        return None
    axis = coarse.cylinder.axis
    on_trunk = np.abs(point_distance(trunk, coarse.cylinder)) < 2 * params.ransac_threshold_m
    h_axis = trunk @ axis
    h_bottom = float(np.percentile(h_axis[on_trunk], 1)) if on_trunk.any() else float(h_axis.min())
    h_top = float(np.percentile(h_axis[on_trunk], 99)) if on_trunk.any() else float(h_axis.max())
    # 4. local ground with the trunk axis prior; the trunk's own surface is never ground
    o_bottom = _axis_at(coarse.cylinder, h_bottom)
    ground = ground_around_trunk(local, o_bottom, coarse.cylinder, ground_params, rng)
    wide = _wide_ground(points, o_bottom, coarse.cylinder, ground_params, rng) if ground is None else None
    return TrunkGround(lm_id, tuple((int(vi), int(di)) for vi, di in members), slab[near][trunk_sel],
                       coarse.cylinder, h_bottom, h_top, ground, wide)


def _axis_at(c: Cylinder, h: float) -> np.ndarray:
    """(3,) the axis point at height h along the axis (p . axis = h)."""
    return c.origin + (h - c.origin @ c.axis) * c.axis


def fit_trunk_cylinders(points: np.ndarray, views: list[TrunkView], intr: CameraIntrinsics, params: TrunkParams,
                        grounds: list[TrunkGround], seed: int) -> list[TrunkLandmark]:
    """Step 5 of the module docstring: each landmark's band cylinder (eq. objectCylinder) at the diameter height
    above its ground, its foot, merge axis and views; `grounds` from `fit_side_grounds` on the same cloud
    (P, 3) and views (in this process or another)."""
    points = _cloud(points)
    return [_fit_band(g, points, views, intr, params, _stream(seed, _BAND_STREAM, g.id)) for g in grounds]


def _fit_band(g: TrunkGround, cloud: np.ndarray, views: list[TrunkView], intr: CameraIntrinsics,
              params: TrunkParams, rng: np.random.Generator) -> TrunkLandmark:
    try:
        obs = [(views[vi], views[vi].detections[di]) for vi, di in g.detections]
        trunk = cloud[np.asarray(g.point_indices, np.int64)]
    except IndexError as err:
        raise TrunkError(f"trunk landmark {g.id}: its ground's detections or points are not in this side's views "
                         f"({len(views)}) and cloud ({len(cloud)} points): {err}") from err
    # each detection's depth pixels in odom, thinned (the merge axis)
    view_points = np.concatenate([P[:: max(1, len(P) // _VIEW_POINTS_PER_DETECTION)]
                                  for P in (_detection_points(v, det, intr) for v, det in obs)])
    normals = _normals(trunk)
    radius_range = (params.radius_min_m, params.radius_max_m)
    flags: list[str] = []
    coarse, axis, h_bottom, h_top = g.coarse, g.coarse.axis, g.bottom_m, g.top_m
    o_bottom = _axis_at(coarse, h_bottom)
    ground = g.ground
    h_lo, h_hi = params.diameter_height_m - params.band_m / 2, params.diameter_height_m + params.band_m / 2
    height_ground = ground  # the plane the diameter height is measured from
    base = o_bottom if ground is None else ground.point
    if ground is None:
        flags.append("no_ground")
        height_ground = g.wide_ground
        if height_ground is not None:
            flags.append("diameter_height_from_wide_ground")
            # the foot on the wider ground rather than the lowest trunk point seen: grass or weeds may hide
            # the foot (the 10-tree standard row: one tree's lowest point 20 cm up its trunk)
            base = height_ground.point
    # The merge axis from the detections' own depth pixels, not the fused cloud: a TSDF surface of a thin
    # trunk is displaced by an amount that grows as the trunk narrows upwards, which leans the fused trunk
    # towards the camera (with true poses and noise-free depth on the standard row: 0.16 deg median at the
    # 4 cm truncation, 2.1 deg at 8 cm; the depth pixels themselves: under 0.08 deg). The foot is left out,
    # where a mask most likely takes in ground or grass (merged standard row: 0.259 -> 0.245 deg).
    above = (height_ground.height_of(view_points) if height_ground is not None
             else view_points @ axis - h_bottom) > FOOT_CLEARANCE_M
    cone, taper = refine_cone_axis(view_points[above], coarse, threshold_m=2 * params.ransac_threshold_m,
                                   sigma_m=params.sigma_3d_m, huber_k=params.huber_k)
    # Without any ground the diameter height is unknown: no diameter rather than one at a guessed height.
    band_h = np.full(len(trunk), np.nan) if height_ground is None else height_ground.height_of(trunk)
    in_band = (band_h >= h_lo) & (band_h <= h_hi)
    band_views: list[CylinderView] = []
    band_pixels: list[int] = []
    for v, det in obs:
        depth = np.asarray(v.depth)
        m = _band_rows_mask(np.asarray(det.mask), depth, intr, v.T_odom_cam, height_ground, h_lo, h_hi, h_bottom,
                            axis)
        band_pixels.append(int((m & (depth > 0)).sum()))
        if m.sum() >= params.min_mask_pixels // 4:
            rect = mask_bounds(m, _VIEW_MARGIN_PX + params.edge_snap_px)
            band_views.append(CylinderView(v.T_odom_cam, ImagePatch.crop(m, rect), ImagePatch.crop(depth, rect)))
    band: CylinderFit | None = None
    baseline: CylinderFit | None = None
    if height_ground is not None and (in_band.sum() < params.min_band_points or not band_views):
        flags.append("hidden_at_diameter_height")
    elif height_ground is not None:
        P, N = trunk[in_band], normals[in_band]
        kw = dict(up=axis, threshold_m=params.ransac_threshold_m, iterations=params.ransac_iterations,
                  max_axis_angle_deg=15.0, radius_range_m=radius_range, sigma_3d_m=params.sigma_3d_m,
                  sigma_px=params.sigma_px, lam=params.lam, huber_k=params.huber_k, edge_snap_px=params.edge_snap_px)
        try:
            baseline = fit_cylinder(P, N, [], intr, rng, use_2d=False, **kw)  # type: ignore[arg-type]
            band = fit_cylinder(P, N, band_views, intr, rng, use_2d=True, initial=baseline.cylinder,
                                **kw) if params.use_2d else baseline  # type: ignore[arg-type]
        except CylinderError:
            flags.append("hidden_at_diameter_height")
            band = baseline = None
    if band is not None and height_ground is not None:
        # The foot below the band's axis point along the merge axis: the merge's trunk line is foot + merge
        # axis. The plain cylinder leans away from the camera, so at the ground its axis sits towards it; the
        # cone's axis from depth pixels alone leaves radius and depth traded off (its surface is mostly the
        # near cap); the band's axis point is pinned by its silhouette (the 2D term). Each side placed on the
        # truth, 10-tree standard row, the two sides' trunk lines at 0.3 m apart in depth by: plain foot 8.1
        # mm, cone 11.1 mm, band 0.4 mm.
        # A band whose axis point strays from the whole trunk's axis by more than BAND_AGREEMENT_M took in
        # something else (weeds at that height: 20 mm on slope_weeds, where the two sides' axes then missed
        # each other by 14 mm after the merge); the plain foot is kept then (others: 0.5-6 mm).
        n, d = height_ground.normal, height_ground.offset
        try:
            at_height = band.cylinder.point_at_height(n, d, params.diameter_height_m)
            off = at_height - coarse.origin
            off -= (off @ axis) * axis
            if np.linalg.norm(off) <= BAND_AGREEMENT_M:
                base = Cylinder(cone.axis, at_height, cone.radius).point_at_height(n, d, 0.0)
        except CylinderError:  # an axis along the ground: the plain foot stays
            pass
    observations = []
    for (v, det), n_band in zip(obs, band_pixels, strict=True):
        cyl_cam = band.cylinder.transformed(np.linalg.inv(v.T_odom_cam)) if band is not None else None
        observations.append(TrunkObservation(v.keyframe, v.stamp, det, cyl_cam, n_band))
    length = float(h_top - (base @ axis))
    return TrunkLandmark(id=g.id, axis=axis, base=base, length_m=length, ground=ground, band=band,
                         diameter_m=2.0 * band.cylinder.radius if band is not None else None,
                         baseline_band=baseline, n_points=len(trunk), observations=observations, flags=flags,
                         band_points=trunk[in_band] if band is not None else None,
                         band_normals=normals[in_band] if band is not None else None,
                         band_views=band_views if band is not None else [],
                         merge_axis=cone.axis * np.sign(cone.axis @ axis), taper=taper)
