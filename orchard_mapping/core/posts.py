"""Trellis post landmarks of one side: what ties a side's sweeps to each other where trunks cannot.

The paper merges on poles where trunks are few. A post is also what a raised sweep (camera at ~3 m,
looking down on the canopy) and the level sweep of the same side both see: the raised sweep sees no
trunk and no ground, only canopy and the upper part of each post. Nothing else in its images ties it to
the level sweep between the row's ends (docs/merge.md), so its drift would stay in the merged map.

Each keyframe given to the detector that holds a post detection fits that post's axis from its own raw
depth (a cylinder, RANSAC then a fixed-radius least-squares refit): a measurement of the post in that
camera's frame, independent of the side's estimated poses. Observations close to each other across the
up direction (placed by the side's poses) form one post landmark. The semantic bundle adjustment
(core/semantic_ba.py) holds each post to one vertical-ish line in map from one keyframe per pass by it.

Frames: `_cam` in the keyframe's colour optical frame; `place` in odom_<side>. Metres.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from orchard_mapping.core.cylinder import Cylinder, CylinderError, fit_cylinder, point_distance
from orchard_mapping.core.odometry import backproject
from orchard_mapping.core.semantic_ba import PostShape, trunk_frame
from orchard_mapping.core.trunks import TrunkLandmark, associate_places
from orchard_mapping.core.types import CameraIntrinsics

__all__ = ["PostLandmark", "PostObservation", "build_post_landmarks", "fit_post_view", "pass_representatives", "post_shapes",
           "passes", "refit_fixed_radius", "separate_trunks_from_posts"]

# px eroded off a post mask before its depth is used: raw depth mixes post and background at the edges
# (flying pixels), and a learned mask's edge strays 2-3 px.
MASK_ERODE_PX = 3
MIN_POINTS = 150  # depth pixels a post view needs (a 10 cm post 4 m away is ~15 px wide)
MAX_POINTS = 1500  # thinned to this many for the fit (enough for a mm-level axis; RANSAC cost grows with it)
MAX_DEPTH_M = 4.5  # m: beyond, the depth noise (~4 mm x z^2) makes the curvature meaningless
THRESHOLD_M = 0.015  # m, RANSAC inlier distance, at least; and at least 2 sd of the depth noise there:
DEPTH_SIGMA_COEFF = 0.004  # depth noise sd / z^2 (1/m): the front end's model (core.odometry.sample_depth)
MIN_INLIER_FRACTION = 0.5
RADIUS_RANGE_M = (0.015, 0.15)  # m: 3-30 cm posts
MAX_AXIS_ANGLE_DEG = 45.0  # deg off the side's up in the camera frame (a raised camera pitches 35 deg)
ASSOCIATE_RADIUS_M = 0.3  # m across up: posts stand metres apart, one post's places scatter by centimetres
MIN_OBSERVATIONS = 3
REFIT_POINTS = 300  # inliers an observation keeps for the fixed-radius refit
PASS_GAP_M = 0.5  # m of camera travel between two observations of a post that starts a new pass by it
# m: a trunk landmark and a post landmark whose axes are closer than their two radii and this (the scatter of
# the two places) cannot be two things standing side by side: they are one the detector called either.
SAME_OBJECT_TOL_M = 0.03


@dataclass(frozen=True)
class PostObservation:
    """One keyframe's fit of one post, from that frame's depth alone."""

    keyframe: int  # keyframe id
    axis_cam: np.ndarray  # (3,) unit, up
    centre_cam: np.ndarray  # (3,) m: the axis point at the middle of the post's part this view saw
    radius_m: float  # m, free fit (poor from one view: the refit holds it to the landmark's median)
    extent_m: float  # m, length of the post seen along the axis
    inliers: int  # depth pixels within THRESHOLD_M of the fit
    points_cam: np.ndarray  # (M, 3) float32 m: inlier depth pixels, thinned to REFIT_POINTS (the landmark's refit)


@dataclass(frozen=True)
class PostLandmark:
    """One trellis post as seen from one side: its observations, each with its own camera-frame axis."""

    id: int  # 0.. along the side
    place: np.ndarray  # (3,) m odom: median of the observations' centres (by the side's poses)
    radius_m: float  # m, median of the observations' free fits
    observations: list[PostObservation]


def fit_post_view(depth: np.ndarray, mask: np.ndarray, intr: CameraIntrinsics, up_cam: np.ndarray, keyframe: int,
                  rng: np.random.Generator, radius_m: float | None = None) -> PostObservation | None:
    """The post of `mask` (H, W) bool in one frame's raw depth (H, W) m, or None when the view cannot fix its
    axis (too few depth pixels, no cylinder, too many outliers). up_cam (3,): the side's up in this camera."""
    import cv2

    m = cv2.erode(np.asarray(mask, np.uint8), np.ones((2 * MASK_ERODE_PX + 1,) * 2, np.uint8)).astype(bool)
    d = np.asarray(depth)
    v, u = np.nonzero(m & (d > 0) & (d < MAX_DEPTH_M))
    if len(v) < MIN_POINTS:
        return None
    if len(v) > MAX_POINTS:
        keep = np.sort(rng.choice(len(v), MAX_POINTS, replace=False))
        v, u = v[keep], u[keep]
    X = backproject(np.stack([u, v], axis=1).astype(float), d[v, u].astype(float), intr)  # (N, 3) camera
    threshold = max(THRESHOLD_M, 2.0 * DEPTH_SIGMA_COEFF * float(np.median(X[:, 2])) ** 2)
    try:
        fit = fit_cylinder(X, _normals(X), [], intr, rng, up=up_cam, threshold_m=threshold, iterations=150,
                           max_axis_angle_deg=MAX_AXIS_ANGLE_DEG, radius_range_m=RADIUS_RANGE_M, use_2d=False)
    except CylinderError:
        return None
    if fit.inliers_3d < MIN_INLIER_FRACTION * len(X):
        return None
    c = fit.cylinder
    inl = np.abs(point_distance(X, c)) < threshold
    h = (X[inl] - c.origin) @ c.axis  # (N_in,) m along the axis
    centre = c.origin + 0.5 * (h.min() + h.max()) * c.axis
    P = X[inl]
    if len(P) > REFIT_POINTS:
        P = P[np.sort(rng.choice(len(P), REFIT_POINTS, replace=False))]
    obs = PostObservation(keyframe, c.axis, centre, float(c.radius), float(h.max() - h.min()), int(inl.sum()),
                          P.astype(np.float32))
    return obs if radius_m is None else refit_fixed_radius(obs, radius_m)


def _normals(X: np.ndarray) -> np.ndarray:
    import open3d as o3d

    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(X))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(0.03, 20))
    return np.asarray(pc.normals)


def refit_fixed_radius(obs: PostObservation, radius_m: float) -> PostObservation:
    """The observation's axis refitted to its kept points with the radius held (Huber).

    One view's free fit gets the radius wrong by the depth noise (a 100 mm post: 91 mm from level views
    at 1-2 m, 77 mm from a raised view at 3 m; standard row, exact masks), and the axis moves along the
    viewing ray with it: axis errors 4.6 / 15 mm median (level / raised). With the radius held at the
    truth they were 0.5 / 3.4 mm."""
    from scipy.optimize import least_squares

    from orchard_mapping.core.cylinder import perpendicular_basis, radial_terms, tilt_shift_jacobian

    e1, e2 = perpendicular_basis(obs.axis_cam)

    def unpack(x: np.ndarray) -> Cylinder:
        a = obs.axis_cam + x[0] * e1 + x[1] * e2
        return Cylinder(a / np.linalg.norm(a), obs.centre_cam + x[2] * e1 + x[3] * e2, radius_m)

    X = obs.points_cam.astype(float)

    def jacobian(x: np.ndarray) -> np.ndarray:
        c = unpack(x)
        rel, h, u, _ = radial_terms(X, c.axis, c.origin)
        return tilt_shift_jacobian(rel, h, u, c.axis, float(np.linalg.norm(obs.axis_cam + x[0] * e1 + x[1] * e2)),
                                    e1, e2)

    sol = least_squares(lambda x: point_distance(X, unpack(x)), np.zeros(4), jac=jacobian, loss="huber",
                        f_scale=0.005)
    c = unpack(sol.x)
    centre = c.origin + float((obs.centre_cam - c.origin) @ c.axis) * c.axis
    return replace(obs, axis_cam=c.axis, centre_cam=centre)


def build_post_landmarks(observations: list[PostObservation], poses: np.ndarray) -> list[PostLandmark]:
    """Post landmarks of one side from its per-frame post fits; poses (K, 4, 4) T_odom_cam.

    Observations are grouped across the posts' mean axis (up); each landmark's radius is the median free
    radius of its nearer half of views (depth noise grows with z^2), and every view is refitted with it."""
    if not observations:
        return []
    places = np.array([poses[o.keyframe][:3, :3] @ o.centre_cam + poses[o.keyframe][:3, 3] for o in observations])
    axes = np.array([poses[o.keyframe][:3, :3] @ o.axis_cam for o in observations])  # (N, 3) odom, all "up"
    up = axes.sum(axis=0) / np.linalg.norm(axes.sum(axis=0))
    label = associate_places(places, up, ASSOCIATE_RADIUS_M)
    groups = sorted((np.flatnonzero(label == k) for k in range(label.max() + 1)),
                    key=lambda g: min(observations[i].keyframe for i in g))
    out = []
    for g in groups:
        if len(g) < MIN_OBSERVATIONS:
            continue
        obs = sorted((observations[i] for i in g), key=lambda o: o.keyframe)
        near = sorted(obs, key=lambda o: float(np.linalg.norm(o.centre_cam)))[: max(1, len(obs) // 2)]
        radius = float(np.median([o.radius_m for o in near]))
        obs = [refit_fixed_radius(o, radius) for o in obs]
        place = np.median([poses[o.keyframe][:3, :3] @ o.centre_cam + poses[o.keyframe][:3, 3] for o in obs], axis=0)
        out.append(PostLandmark(len(out), place, radius, obs))
    return out


def passes(post: PostLandmark, poses: np.ndarray) -> list[list[PostObservation]]:
    """The post's observations split into passes by it: a new pass where the camera moved more than
    PASS_GAP_M between two consecutive observations (a side's level and raised sweeps pass a post metres
    apart in time and 1-2 m apart in space; frames within a pass are ~0.15 m apart)."""
    out: list[list[PostObservation]] = [[post.observations[0]]]
    for a, b in zip(post.observations, post.observations[1:], strict=False):  # each with the next
        if np.linalg.norm(poses[b.keyframe][:3, 3] - poses[a.keyframe][:3, 3]) > PASS_GAP_M:
            out.append([])
        out[-1].append(b)
    return out


def pass_representatives(post: PostLandmark, poses: np.ndarray) -> list[PostObservation]:
    """One observation per pass by the post: the one whose place (by the side's poses) is nearest the
    pass's median place. Within a pass (a few metres of travel) the side barely drifts, so a view far
    from the others is a bad fit (a mask that took in a branch), not the post moving."""
    out = []
    for p in passes(post, poses):
        P = np.array([poses[o.keyframe][:3, :3] @ o.centre_cam + poses[o.keyframe][:3, 3] for o in p])
        out.append(p[int(np.argmin(np.linalg.norm(P - np.median(P, axis=0), axis=1)))])
    return out


def post_shapes(sides: list[tuple[list[PostLandmark], np.ndarray]], pair_radius_m: float = ASSOCIATE_RADIUS_M,
                across_sides: bool = False) -> list[list[PostShape]]:
    """What the semantic BA measures of the posts: per side (its landmarks, its keyframe poses (K, 4, 4)
    T_map_cam after the initial transform), one PostShape per pass. With across_sides, posts of different
    sides within pair_radius_m of each other across up (map) are one post; by default each side's posts
    tie only that side's sweeps. (Paired across the sides on the 10-tree standard row, the merged map
    came out 0.248 deg off, 0.077 without: a side's views put the axis a few mm towards its own cameras,
    the radius they share being 4-5 mm small, so the two sides' halves of a post stand ~9 mm apart while
    their trunks, fitted with the silhouette terms, meet.) Every view of a post puts its frame's origin
    at the point of its own axis nearest the post's reference point (the mean of the views' centres), so
    that a view's tilt error is not levered by the metre between what a level and a raised view see."""
    reps = [[(lm, pass_representatives(lm, poses)) for lm in lms] for lms, poses in sides]

    def centres(k: int, obs: list[PostObservation]) -> np.ndarray:
        poses = sides[k][1]
        return np.array([poses[o.keyframe][:3, :3] @ o.centre_cam + poses[o.keyframe][:3, 3] for o in obs])

    axes = [sides[k][1][o.keyframe][:3, :3] @ o.axis_cam for k in range(len(sides)) for _, obs in reps[k] for o in obs]
    if not axes:
        return [[] for _ in sides]
    up = np.sum(axes, axis=0) / np.linalg.norm(np.sum(axes, axis=0))
    ids: list[list[int]] = []
    places: list[np.ndarray] = []  # (3,) per post id, map, for pairing
    for k in range(len(sides)):
        mine = []
        taken: set[int] = set(range(len(places))) if not across_sides else set()
        for _, obs in reps[k]:
            c = np.median(centres(k, obs), axis=0)
            flat = [(np.linalg.norm((q - c) - ((q - c) @ up) * up), i) for i, q in enumerate(places) if i not in taken]
            d, i = min(flat, default=(np.inf, -1))
            if d > pair_radius_m:
                i = len(places)
                places.append(c)
            taken.add(i)
            mine.append(i)
        ids.append(mine)
    refs: dict[int, list[np.ndarray]] = {}
    for k in range(len(sides)):
        for (_, obs), i in zip(reps[k], ids[k], strict=True):
            refs.setdefault(i, []).extend(centres(k, obs))
    out: list[list[PostShape]] = []
    for k, (_, poses) in enumerate(sides):
        shapes = []
        for (_, obs), i in zip(reps[k], ids[k], strict=True):
            p_ref = np.mean(refs[i], axis=0)
            for o in obs:
                T_cam_map = np.linalg.inv(poses[o.keyframe])
                q = T_cam_map[:3, :3] @ p_ref + T_cam_map[:3, 3]
                origin = o.centre_cam + float((q - o.centre_cam) @ o.axis_cam) * o.axis_cam
                shapes.append(PostShape(i, o.keyframe, trunk_frame(origin, o.axis_cam, -origin)))
        out.append(shapes)
    return out


def _across(v: np.ndarray, direction: np.ndarray) -> float:
    """m, the part of v (3,) across the unit direction (3,): a point's distance to a line through the other."""
    return float(np.linalg.norm(v - (v @ direction) * direction))


def separate_trunks_from_posts(trunks: list[TrunkLandmark], posts: list[PostLandmark], poses: np.ndarray
                               ) -> tuple[list[TrunkLandmark], list[PostLandmark], list[str]]:
    """One side's trunk and post landmarks without the objects that are in both.

    The detector may call a post a trunk in some frames and a post in others (grey posts look like grey
    trunks). A trunk and a post whose axes pass closer than their radii and SAME_OBJECT_TOL_M are one
    object, and the frames that saw it decide what it is, a tie going to the post: a post must never be
    taken for a trunk. The post's views from a raised sweep count: what shows as a post above the canopy
    is one (the slope_weeds row of seed 1, front side: a post was a trunk in 8 level frames, a post in 1
    level and 13 raised ones, and was reported as a 99 mm trunk). Kept trunks are numbered 0.. along the side
    again, posts likewise. Returns (trunks, posts, one line per object given up). poses (K, 4, 4) T_odom_cam."""
    axes = []  # (3,) unit odom per post: the mean of its views' axes
    for p in posts:
        a = np.sum([poses[o.keyframe][:3, :3] @ o.axis_cam for o in p.observations], axis=0)
        axes.append(a / np.linalg.norm(a))
    drop_trunks: set[int] = set()
    drop_posts: set[int] = set()
    post_frames: dict[int, int] = {}  # trunk id -> frames of the posts given to it
    said: list[str] = []
    for t in trunks:
        r_trunk = t.diameter_m / 2 if t.diameter_m is not None else None
        for p, a in zip(posts, axes, strict=True):
            if p.id in drop_posts:
                continue
            # m, the trunk's foot to the post's axis line, or the post's place to the trunk's axis line, the
            # nearer: the post's place is halfway up what its views saw (metres above the foot), where an axis
            # off by a degree or two misses by centimetres. Either axis can be the one off: the trunk's of a
            # short band, the post's mean of few views (slope_weeds seed 1, back side, flip test: a post's
            # views' mean axis 4 deg off put its foot 138 mm from the trunk it had been called in 3 frames;
            # along the trunk's axis the two are 17 mm apart).
            rel = t.base - p.place
            gap = min(_across(rel, a), _across(rel, t.axis))
            if gap > p.radius_m + (p.radius_m if r_trunk is None else r_trunk) + SAME_OBJECT_TOL_M:
                continue
            as_post, as_trunk = len(p.observations), len(t.observations)
            if as_post >= as_trunk:
                drop_trunks.add(t.id)
                said.append(f"trunk {t.id} is post {p.id} ({gap * 1000:.0f} mm apart): a post in {as_post} frames, "
                            f"a trunk in {as_trunk}; reported as a post")
                break
            drop_posts.add(p.id)
            post_frames[t.id] = post_frames.get(t.id, 0) + as_post
            said.append(f"post {p.id} is trunk {t.id} ({gap * 1000:.0f} mm apart): a trunk in {as_trunk} frames, "
                        f"a post in {as_post}; not used as a post")
    kept_trunks = [replace(t, id=i, post_frames=t.post_frames + post_frames.get(t.id, 0))
                   for i, t in enumerate(t for t in trunks if t.id not in drop_trunks)]
    kept_posts = [replace(p, id=i) for i, p in enumerate(p for p in posts if p.id not in drop_posts)]
    return kept_trunks, kept_posts, said
