"""Trunk cylinder fitting (paper: "Trunk Cylinder Modeling", eq. objectCylinder).

A trunk segment is a straight cylinder d: axis n_d (unit, up), origin O_d (a
point on the axis) and radius r_d. It is fitted in two steps:

1. RANSAC with a minimal solver on the 3D points: two points with their
   surface normals fix a cylinder (the axis is perpendicular to both normals;
   the centre is where the two normal lines meet in the plane across the axis),
   as PCL's SAC cylinder model does. The paper names Beder and Foerstner's
   nine-point quadric solver; two oriented points need far fewer samples for
   the same confidence, and the normals of the fused cloud are smooth.
2. Levenberg-Marquardt with a Huber loss on eq. objectCylinder:
     sum_p rho(e_d(X_p)^2 / s3^2) + lambda * sum_p rho(||x_p - p_r(X_p)||^2 / s2^2)
   where e_d is a point's distance to the cylinder surface and p_r projects a
   depth pixel's 3D point X_p radially onto the surface and back into the
   image: at the trunk's silhouette the radial direction is across the viewing
   ray, so the 2D term pins the radius to the edges the detector sees. A third
   term (the "boundary" of the issue: the mask's left and right edges) asks the
   viewing ray through each edge pixel to touch the cylinder; edges made by an
   occluder in front of the trunk (an occlusion boundary) are left out. A learned
   mask's edges stray a few pixels from the trunk's; each edge is first moved
   to the trunk's depth discontinuity within `edge_snap_px` (exact masks stay put).
   With `use_2d=False` only the 3D term remains: the paper's baseline, which
   gives trunks too large (noise on the visible half-surface pulls the radius out).

Frames: the 3D points and the cylinder in one frame (odom_<side>); each view
carries T_odom_cam of its camera (colour optical frame). Metres, pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from orchard_mapping.core.geometry import group_medians
from orchard_mapping.core.odometry import backproject
from orchard_mapping.core.types import CameraIntrinsics, ImagePatch
from orchard_mapping.errors import OrchardMappingError

__all__ = [
    "Cylinder",
    "CylinderError",
    "CylinderFit",
    "CylinderView",
    "cylinder_from_oriented_points",
    "fit_cylinder",
    "fit_cylinders_shared_radius",
    "perpendicular_basis",
    "point_distance",
    "ransac_cylinder",
    "refine_cone_axis",
    "view_residuals",
]


class CylinderError(OrchardMappingError):
    """A cylinder cannot be fitted from the given data."""


@dataclass(frozen=True)
class Cylinder:
    axis: np.ndarray  # (3,) unit, up
    origin: np.ndarray  # (3,) m, a point on the axis
    radius: float  # m

    def transformed(self, T_b_a: np.ndarray) -> "Cylinder":
        """The same cylinder in frame b, given T_b_a (4, 4) and this cylinder in frame a."""
        R, t = T_b_a[:3, :3], T_b_a[:3, 3]
        return Cylinder(R @ self.axis, R @ self.origin + t, self.radius)

    def point_at_height(self, plane_normal: np.ndarray, plane_offset: float, height: float) -> np.ndarray:
        """(3,) the axis point `height` m above the plane n . p + d = 0 (n up)."""
        denom = float(self.axis @ plane_normal)
        if abs(denom) < 1e-6:
            raise CylinderError("the cylinder axis is parallel to the ground plane")
        s = (height - (self.origin @ plane_normal + plane_offset)) / denom
        return self.origin + s * self.axis


@dataclass(frozen=True)
class CylinderView:
    """One camera's view of a trunk segment: the detection mask and the depth of that frame (raw or cleaned)."""

    T_odom_cam: np.ndarray  # (4, 4) camera pose
    mask: np.ndarray | ImagePatch  # (H, W) bool, the trunk's instance mask
    depth: np.ndarray | ImagePatch  # (H, W) float32 m, 0 = none


@dataclass(frozen=True)
class CylinderFit:
    cylinder: Cylinder
    inliers_3d: int  # 3D points within the RANSAC threshold of the final cylinder
    rmse_3d_m: float  # m, RMS distance of those points to the surface
    rmse_2d_px: float  # px, RMS of the 2D terms (NaN without views)
    n_2d: int  # 2D residuals used (depth pixels + boundary pixels)
    used_2d: bool


def point_distance(points: np.ndarray, cyl: Cylinder) -> np.ndarray:
    """(N,) signed distance (m) of points (N, 3) to the cylinder surface (positive outside)."""
    rel = points - cyl.origin  # (N, 3)
    radial = rel - (rel @ cyl.axis)[:, None] * cyl.axis
    return np.linalg.norm(radial, axis=1) - cyl.radius


def radial_terms(points: np.ndarray, axis: np.ndarray, origin: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """rel (N, 3) points from the origin, h (N,) m along the axis, u (N, 3) unit radial directions, d (N,)
    radial distances of points (N, 3) from the axis line."""
    rel = points - origin
    h = rel @ axis
    q = rel - h[:, None] * axis
    d = np.maximum(np.linalg.norm(q, axis=1), 1e-12)
    return rel, h, q / d[:, None], d


def tilt_shift_jacobian(rel: np.ndarray, h: np.ndarray, u: np.ndarray, axis: np.ndarray, axis_length: float,
                         e1: np.ndarray, e2: np.ndarray, taper: float = 0.0) -> np.ndarray:
    """(N, 4) derivatives of each point's radial distance minus taper * h (a cone's radius change along the
    axis; 0 for a cylinder) with respect to (the axis tilted along e1, e2 before it is normalised from
    axis_length; the origin moved along e1, e2). Analytic, since u is across the axis: d|q| = u . dq; by
    finite differences the fits spent most of their time here (a residual evaluation per parameter)."""
    J = np.empty((len(rel), 4))
    for i, e in enumerate((e1, e2)):
        g = (e - (axis @ e) * axis) / axis_length  # d axis / d tilt
        J[:, i] = -h * (u @ g) - taper * (rel @ g)
        J[:, 2 + i] = -(u @ e) + taper * (axis @ e)
    return J


def cylinder_from_oriented_points(p: np.ndarray, n: np.ndarray, up: np.ndarray | None = None) -> Cylinder | None:
    """The cylinder through two points p (2, 3) with surface normals n (2, 3); None if degenerate."""
    axes, centres, radii, ok = _cylinders_from_oriented_pairs(p[None], n[None], up)
    return Cylinder(axes[0], centres[0], float(radii[0])) if ok[0] else None


def _cylinders_from_oriented_pairs(p: np.ndarray, n: np.ndarray, up: np.ndarray | None
                                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The cylinders through S pairs of points p (S, 2, 3) with surface normals n (S, 2, 3), at once:
    axes (S, 3) unit (towards up), centres (S, 3) on the axes, radii (S,), ok (S,) False where degenerate."""
    axis = np.cross(n[:, 0], n[:, 1])  # (S, 3)
    s = np.linalg.norm(axis, axis=1)
    ok = s >= 0.05  # normals nearly parallel: the axis is undetermined
    axis = axis / np.where(ok, s, 1.0)[:, None]
    if up is not None:
        axis *= np.where(axis @ up < 0, -1.0, 1.0)[:, None]
    # In the plane across the axis, the centre lies on both normal lines p_i + t_i m_i: least squares in
    # (t_0, t_1) of m_0 t_0 - m_1 t_1 = q_1 - q_0, by its 2 x 2 normal equations.
    q = p - np.einsum("sk,sj->skj", np.einsum("skj,sj->sk", p, axis), axis)  # (S, 2, 3) projected points
    m = n - np.einsum("sk,sj->skj", np.einsum("skj,sj->sk", n, axis), axis)
    m /= np.maximum(np.linalg.norm(m, axis=2, keepdims=True), 1e-12)
    c01 = np.einsum("sj,sj->s", m[:, 0], m[:, 1])  # m_i are unit: the normal matrix is [[1, -c], [-c, 1]]
    b = q[:, 1] - q[:, 0]
    b0, b1 = np.einsum("sj,sj->s", m[:, 0], b), -np.einsum("sj,sj->s", m[:, 1], b)
    det = np.where(ok, 1.0 - c01**2, 1.0)
    t0, t1 = (b0 + c01 * b1) / det, (c01 * b0 + b1) / det
    centre = 0.5 * (q[:, 0] + t0[:, None] * m[:, 0] + q[:, 1] + t1[:, None] * m[:, 1])
    r = 0.5 * (np.linalg.norm(q[:, 0] - centre, axis=1) + np.linalg.norm(q[:, 1] - centre, axis=1))
    return axis, centre, r, ok


def ransac_cylinder(points: np.ndarray, normals: np.ndarray, rng: np.random.Generator, *, threshold_m: float,
                    iterations: int, up: np.ndarray, max_axis_angle_deg: float,
                    radius_range_m: tuple[float, float], normal_angle_deg: float = 30.0
                    ) -> tuple[Cylinder, np.ndarray] | None:
    """Best cylinder over `iterations` two-point samples: most points (N, 3) within threshold_m whose
    normals (N, 3) point away from the axis within normal_angle_deg; axis within max_axis_angle_deg of
    `up`, radius in radius_range_m. Returns (cylinder, inlier mask (N,)) or None."""
    n_pts = len(points)
    if n_pts < 2:
        return None
    cos_axis = np.cos(np.radians(max_axis_angle_deg))
    cos_normal = np.cos(np.radians(normal_angle_deg))
    pairs = rng.integers(0, n_pts, size=(iterations, 2))
    # every sample's cylinder at once (one at a time this was a third of the fit's time); scored in order
    axes, centres, radii, ok = _cylinders_from_oriented_pairs(points[pairs], normals[pairs], up)
    ok &= (pairs[:, 0] != pairs[:, 1]) & (axes @ up >= cos_axis) & (radii >= radius_range_m[0]) \
        & (radii <= radius_range_m[1])
    cand = np.flatnonzero(ok)
    if len(cand) == 0:
        return None
    scores = np.zeros(len(cand), int)
    step = max(1, _SCORE_BLOCK // n_pts)  # candidates scored together: (step, N) arrays
    for s in range(0, len(cand), step):
        c = cand[s:s + step]
        rel = points[None] - centres[c][:, None]  # (C, N, 3)
        radial = rel - np.einsum("cnj,cj->cn", rel, axes[c])[..., None] * axes[c][:, None]
        dist = np.linalg.norm(radial, axis=2)  # (C, N)
        outward = np.abs(np.einsum("cnj,nj->cn", radial, normals)) / np.maximum(dist, 1e-9)
        scores[s:s + step] = np.sum((np.abs(dist - radii[c][:, None]) < threshold_m) & (outward >= cos_normal), 1)
    i = cand[int(np.argmax(scores))]  # the first sample with the most inliers
    cyl = Cylinder(axes[i], centres[i], float(radii[i]))
    return cyl, _inliers(points, normals, cyl, threshold_m, cos_normal)


# point-candidate pairs scored in one block by RANSAC: ~20 MB of float64 temporaries
_SCORE_BLOCK = 250_000


def _inliers(points: np.ndarray, normals: np.ndarray, cyl: Cylinder, threshold_m: float,
             cos_normal: float) -> np.ndarray:
    rel = points - cyl.origin
    radial = rel - (rel @ cyl.axis)[:, None] * cyl.axis  # (N, 3)
    dist = np.linalg.norm(radial, axis=1)
    outward = np.abs(np.einsum("ij,ij->i", radial, normals)) / np.maximum(dist, 1e-9)  # |cos| (normals unsigned)
    return (np.abs(dist - cyl.radius) < threshold_m) & (outward >= cos_normal)


# --------------------------------------------------------------------------- 2D terms of eq. objectCylinder

@dataclass(frozen=True)
class _ViewData:
    T_cam_odom: np.ndarray  # (4, 4)
    X: np.ndarray  # (M, 3) m camera frame: depth pixels inside the mask
    uv: np.ndarray  # (M, 2) px: those pixels
    rays: np.ndarray  # (B, 3) unit, camera frame: viewing rays through the mask's silhouette edges
    edge_depth: np.ndarray  # (B,) m: trunk depth beside each edge pixel (px -> m scale)


def _prepare_view(view: CylinderView, intr: CameraIntrinsics, rng: np.random.Generator, max_pixels: int,
                  snap_px: int = 0) -> _ViewData:
    mask = np.asarray(view.mask, bool)
    depth = np.asarray(view.depth, np.float32)
    if mask.shape != depth.shape or mask.shape != (intr.height, intr.width):
        raise CylinderError(f"view mask {mask.shape} and depth {depth.shape} must both be "
                            f"({intr.height}, {intr.width})")
    T_cam_odom = np.linalg.inv(view.T_odom_cam)
    v, u = np.nonzero(mask & (depth > 0))
    if len(u) > max_pixels:
        keep = np.sort(rng.choice(len(u), max_pixels, replace=False))
        u, v = u[keep], v[keep]
    uv = np.stack([u, v], 1).astype(float)
    rays, edge_z = _silhouette_rays(mask, depth, intr, snap_px=snap_px)
    return _ViewData(T_cam_odom, backproject(uv, depth[v, u].astype(float), intr), uv, rays, edge_z)


def _snap_edge(row: np.ndarray, u_in: int, step: int, snap_px: int, z_core: float, jump_m: float,
               behind_m: float) -> int:
    """The last trunk pixel of a row at a mask edge, moved to the depth discontinuity within snap_px.

    Outward while the depth continues smoothly from the trunk (the mask stopped short of the trunk's
    edge); else inward past pixels far behind the trunk (the mask bled onto the background). Missing
    depth stops the walk outward and is not taken for background: sensors drop pixels at depth edges.
    jump_m: across a trunk (radius 2-8 cm, 0.8-3 m away) depth changes by under 1 cm per pixel up
    to its last pixel, and what lies behind a trunk at breast height is 10 cm or more farther.
    behind_m: a pixel this far behind the trunk's median depth on its row is not on the trunk.
    """
    W = len(row)
    u = u_in
    while abs(u + step - u_in) <= snap_px and 0 <= u + step < W and row[u + step] > 0 and row[u] > 0 \
            and abs(row[u + step] - row[u]) < jump_m and row[u + step] < z_core + behind_m:
        u += step
    if u != u_in:
        return u
    while abs(u - step - u_in) <= snap_px and row[u] > z_core + behind_m and 0 <= u - step < W:
        u -= step
    return u


def _row_medians(values: np.ndarray, mask: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(R,) the median of values (H, W) over mask (H, W) bool in each of `rows` (R,), NaN where a row has none."""
    v, u = np.nonzero(mask[rows])  # v: index into rows
    out = np.full(len(rows), np.nan)
    if len(v):
        r, med = group_medians(v, values[rows[v], u])
        out[r] = med
    return out


def _silhouette_rays(mask: np.ndarray, depth: np.ndarray, intr: CameraIntrinsics, *, look_px: int = 8,
                     occluder_margin_m: float = 0.05, snap_px: int = 0, jump_m: float = 0.03,
                     behind_m: float = 0.20) -> tuple[np.ndarray, np.ndarray]:
    """Viewing rays through the left and right edges of the mask, one per row and side.

    An edge is kept only where it is the trunk's own silhouette: not at the image border, the trunk
    has depth just inside it, and the first valid depth outside (within look_px) is not in front of
    the trunk (that would be an occlusion boundary: a leaf or weed hides the trunk's edge).
    """
    H, W = mask.shape
    rows = np.flatnonzero(mask.any(axis=1))
    first = np.argmax(mask[rows], axis=1)  # (R,) each row's first and last mask column
    last = W - 1 - np.argmax(mask[rows, ::-1], axis=1)
    z_core = _row_medians(depth, mask & (depth > 0), rows) if snap_px else None  # (R,) NaN: no depth
    rays, zs = [], []
    for i, v in enumerate(rows):
        if snap_px and not np.isfinite(z_core[i]):
            continue
        for u_in, step in ((first[i], -1), (last[i], 1)):
            if snap_px:
                u_in = _snap_edge(depth[v], int(u_in), step, snap_px, float(z_core[i]), jump_m, behind_m)
            if u_in + step < 0 or u_in + step >= W:
                continue
            inside = depth[v, max(0, min(u_in, u_in - 3 * step)):max(u_in, u_in - 3 * step) + 1]
            inside = np.sort(inside[inside > 0])
            if len(inside) == 0:
                continue
            z_in = 0.5 * float(inside[(len(inside) - 1) // 2] + inside[len(inside) // 2])  # their median
            out = depth[v, u_in + step::step][:look_px] if step > 0 else depth[v, u_in - 1::-1][:look_px]
            out = out[out > 0]
            if len(out) and out[0] < z_in - occluder_margin_m:
                continue  # an occlusion boundary
            u_edge = u_in + 0.5 * step  # the pixel border between trunk and background
            rays.append([(u_edge - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, 1.0])
            zs.append(z_in)
    if not rays:
        return np.zeros((0, 3)), np.zeros(0)
    r = np.asarray(rays)
    return r / np.linalg.norm(r, axis=1, keepdims=True), np.asarray(zs)


def view_residuals(cyl_cam: Cylinder, X: np.ndarray, uv: np.ndarray, rays: np.ndarray, edge_z: np.ndarray,
                   intr: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """The 2D terms of one view, in px: (M, 2) depth-pixel reprojection x_p - p_r(X_p), (B,) edge rays.

    cyl_cam: the cylinder in this camera's frame; X (M, 3) depth points with pixels uv (M, 2);
    rays (B, 3) unit rays through silhouette edges with the trunk depth edge_z (B,) beside them.
    """
    return _StackedViews.of([_ViewData(np.eye(4), X, uv, rays, edge_z)], intr).residuals(cyl_cam, intr)


# --------------------------------------------------------------------------- joint refinement

def perpendicular_basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(e1, e2): two unit vectors (3,) across the unit axis a (3,) and across each other (the directions an
    axis is tilted and moved in by the fits)."""
    h = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(a, h)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


@dataclass(frozen=True)
class _StackedViews:
    """The 2D terms' data of several prepared views stacked in odom, so that one cylinder's terms over all
    of them are a few array operations (view by view, the Python loop was most of the refinement's time)."""

    X: np.ndarray  # (M, 3) m odom: the depth pixels' points
    uv: np.ndarray  # (M, 2) px: their pixels
    R_cam_odom: np.ndarray  # (M, 3, 3): each pixel's camera rotation
    t_cam_odom: np.ndarray  # (M, 3) m
    ray_origin: np.ndarray  # (B, 3) m odom: the camera centre of each silhouette-edge ray
    ray_dir: np.ndarray  # (B, 3) unit odom
    px_per_m: np.ndarray  # (B,) fx / the trunk depth beside the edge

    @staticmethod
    def of(data: list[_ViewData], intr: CameraIntrinsics) -> "_StackedViews":
        T = [np.linalg.inv(d.T_cam_odom) for d in data]  # T_odom_cam per view
        m = [len(d.X) for d in data]
        b = [len(d.rays) for d in data]
        X = [d.X @ Ti[:3, :3].T + Ti[:3, 3] for d, Ti in zip(data, T, strict=True)]
        return _StackedViews(
            X=np.concatenate(X) if X else np.zeros((0, 3)),
            uv=np.concatenate([d.uv for d in data]) if data else np.zeros((0, 2)),
            R_cam_odom=np.repeat(np.array([d.T_cam_odom[:3, :3] for d in data]).reshape(-1, 3, 3), m, axis=0),
            t_cam_odom=np.repeat(np.array([d.T_cam_odom[:3, 3] for d in data]).reshape(-1, 3), m, axis=0),
            ray_origin=np.repeat(np.array([Ti[:3, 3] for Ti in T]).reshape(-1, 3), b, axis=0),
            ray_dir=np.concatenate([d.rays @ Ti[:3, :3].T for d, Ti in zip(data, T, strict=True)]) if data else np.zeros((0, 3)),
            px_per_m=(intr.fx / np.maximum(np.concatenate([d.edge_depth for d in data]), 1e-3)) if data
            else np.zeros(0))

    def _surface(self, cyl: Cylinder) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """rel (M, 3) pixel points from the origin, along (M,) m along the axis, w (M, 3) unit radial
        directions, dist (M,) m from the axis, S (M, 3) their surface points in each pixel's camera."""
        a, O, r = cyl.axis, cyl.origin, cyl.radius
        rel = self.X - O
        along = rel @ a
        radial = rel - along[:, None] * a
        dist = np.maximum(np.linalg.norm(radial, axis=1), 1e-9)
        w = radial / dist[:, None]
        S = np.einsum("mij,mj->mi", self.R_cam_odom, O + along[:, None] * a + r * w) + self.t_cam_odom
        return rel, along, w, dist, S

    def residuals(self, cyl: Cylinder, intr: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
        """(M, 2) px depth-pixel terms and (B,) px edge terms of `cyl` (odom), as `view_residuals` gives them
        view by view (distances and the projection do not depend on the frame they are computed in)."""
        a, O, r = cyl.axis, cyl.origin, cyl.radius
        S = self._surface(cyl)[4]
        z = np.maximum(S[:, 2], 1e-3)
        res_px = self.uv - np.stack([intr.fx * S[:, 0] / z + intr.cx, intr.fy * S[:, 1] / z + intr.cy], axis=1)
        c = np.cross(self.ray_dir, a)  # (B, 3)
        cn = np.maximum(np.linalg.norm(c, axis=1), 1e-9)
        d_line = np.abs(np.einsum("bj,bj->b", c, self.ray_origin - O)) / cn  # ray line to axis line
        return res_px, (d_line - r) * self.px_per_m

    def jacobian(self, cyl: Cylinder, intr: CameraIntrinsics, axis_steps: tuple[np.ndarray, np.ndarray],
                 shift_steps: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Derivatives of `residuals` ((M, 2, 5) and (B, 5)) with respect to: the axis moved by the two
        axis_steps (d axis / d parameter, (3,) each), the origin moved along the two shift_steps (3,), the
        radius. Closed form: by finite differences the 2D fits spent half their time on them."""
        a, O, r = cyl.axis, cyl.origin, cyl.radius
        rel, along, w, dist, Y = self._surface(cyl)
        z = np.maximum(Y[:, 2], 1e-3)
        # d radial per parameter (M, 3, 4): tilting the axis by g, moving the origin by e
        dR = np.stack([-(rel @ g)[:, None] * a - along[:, None] * g for g in axis_steps]
                      + [np.broadcast_to(-(e - (e @ a) * a), rel.shape) for e in shift_steps], axis=2)
        # the surface point S = X - radial + r w moves by -dR + (r / dist) (dR - (w . dR) w); the radius by w
        k = (r / dist)[:, None, None]
        dS = -dR + k * (dR - np.einsum("mi,mip->mp", w, dR)[:, None, :] * w[:, :, None])
        dS = np.concatenate([dS, w[:, :, None]], axis=2)  # (M, 3, 5)
        dY = np.einsum("mij,mjp->mip", self.R_cam_odom, dS)
        J_px = -np.stack([intr.fx * (dY[:, 0] * z[:, None] - Y[:, [0]] * dY[:, 2]),
                          intr.fy * (dY[:, 1] * z[:, None] - Y[:, [1]] * dY[:, 2])], axis=1) / (z**2)[:, None, None]
        c = np.cross(self.ray_dir, a)  # (B, 3)
        cn = np.maximum(np.linalg.norm(c, axis=1), 1e-9)
        D = self.ray_origin - O
        sgn = np.sign(np.einsum("bj,bj->b", c, D))
        s_abs = np.abs(np.einsum("bj,bj->b", c, D))
        J_edge = np.empty((len(c), 5))
        for p, g in enumerate(axis_steps):
            dc = np.cross(self.ray_dir, g)
            J_edge[:, p] = sgn * np.einsum("bj,bj->b", dc, D) / cn - s_abs * np.einsum("bj,bj->b", c, dc) / cn**3
        for p, e in enumerate(shift_steps):
            J_edge[:, 2 + p] = -sgn * (c @ e) / cn
        J_edge[:, 4] = -1.0
        return J_px, J_edge * self.px_per_m[:, None]


def _refine(parts: list[tuple[Cylinder, np.ndarray, list[_ViewData]]], intr: CameraIntrinsics, *,
            sigma_3d_m: float, w2: float, huber_k: float) -> list[Cylinder]:
    """LM with Huber loss on eq. objectCylinder over cylinders that share one radius: each part (its
    initial cylinder, 3D-term points (N, 3), prepared views) has its own axis and origin (4 parameters,
    across its initial axis); the radius is common (eq. objectCylinderFB for two sides; one part is
    eq. objectCylinder)."""
    bases = [perpendicular_basis(c0.axis) for c0, _, _ in parts]
    r0 = float(np.mean([c0.radius for c0, _, _ in parts]))
    stacked = [_StackedViews.of(data, intr) if data else None for _, _, data in parts]

    def unpack(x: np.ndarray) -> list[Cylinder]:
        out = []
        for i, ((c0, _, _), (e1, e2)) in enumerate(zip(parts, bases, strict=True)):
            a = c0.axis + x[4 * i] * e1 + x[4 * i + 1] * e2
            a /= np.linalg.norm(a)
            out.append(Cylinder(a, c0.origin + x[4 * i + 2] * e1 + x[4 * i + 3] * e2, r0 + x[-1]))
        return out

    def residuals(x: np.ndarray) -> np.ndarray:
        res = []
        for (_, P, _), views, cyl in zip(parts, stacked, unpack(x), strict=True):
            res.append(point_distance(P, cyl) / sigma_3d_m)
            if views is not None:
                r_px, r_edge = views.residuals(cyl, intr)
                res += [w2 * r_px.ravel(), w2 * r_edge]
        return np.concatenate(res)

    def jacobian(x: np.ndarray) -> np.ndarray:
        blocks = []
        for i, ((c0, P, _), (e1, e2), views, cyl) in enumerate(zip(parts, bases, stacked, unpack(x), strict=True)):
            a_len = float(np.linalg.norm(c0.axis + x[4 * i] * e1 + x[4 * i + 1] * e2))
            rel, h, u, _ = radial_terms(P, cyl.axis, cyl.origin)
            J_part = [np.column_stack([tilt_shift_jacobian(rel, h, u, cyl.axis, a_len, e1, e2), -np.ones(len(P))])
                      / sigma_3d_m]
            if views is not None:
                steps = tuple((e - (cyl.axis @ e) * cyl.axis) / a_len for e in (e1, e2))
                J_px, J_edge = views.jacobian(cyl, intr, steps, (e1, e2))  # type: ignore[arg-type]
                J_part += [w2 * J_px.reshape(-1, 5), w2 * J_edge]
            J = np.concatenate(J_part)  # (rows of part i, 5): its own 4 parameters and the common radius
            full = np.zeros((len(J), len(x)))
            full[:, 4 * i:4 * i + 4], full[:, -1] = J[:, :4], J[:, 4]
            blocks.append(full)
        return np.concatenate(blocks)

    sol = least_squares(residuals, np.zeros(4 * len(parts) + 1), jac=jacobian, loss="huber", f_scale=huber_k,
                        method="trf", x_scale=[0.05, 0.05, 0.01, 0.01] * len(parts) + [0.005], max_nfev=100)
    return unpack(sol.x)


def refine_cone_axis(points: np.ndarray, cyl: Cylinder, *, threshold_m: float, sigma_m: float = 0.003,
                     huber_k: float = 1.345) -> tuple[Cylinder, float]:
    """The axis of a tapered trunk: LM over axis, origin, radius and taper of a cone (radius r + k h at
    h along the axis from the origin) on the points (N, 3) within threshold_m of `cyl`.

    A cylinder fitted to the visible half of a tapered trunk tilts away from the camera (its near surface
    recedes as the radius shrinks upwards): by the taper's half-angle, 0.3-0.4 deg on the simulated rows,
    in opposite directions on the two sides of a row. The cone's radius change shows in the width of the
    visible surface, so taper and tilt separate. Returns (the cylinder with the cone's axis and its
    radius at the origin, k in m per m)."""
    P = np.asarray(points, float)
    P = P[np.abs(point_distance(P, cyl)) < threshold_m]
    if len(P) < 20:
        return cyl, 0.0
    e1, e2 = perpendicular_basis(cyl.axis)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
        a = cyl.axis + x[0] * e1 + x[1] * e2
        return a / np.linalg.norm(a), cyl.origin + x[2] * e1 + x[3] * e2, cyl.radius + x[4], x[5]

    def residuals(x: np.ndarray) -> np.ndarray:
        a, o, r, k = unpack(x)
        _, h, _, d = radial_terms(P, a, o)
        return (d - (r + k * h)) / sigma_m

    def jacobian(x: np.ndarray) -> np.ndarray:
        a, o, _, k = unpack(x)
        rel, h, u, _ = radial_terms(P, a, o)
        a_len = float(np.linalg.norm(cyl.axis + x[0] * e1 + x[1] * e2))
        return np.column_stack([tilt_shift_jacobian(rel, h, u, a, a_len, e1, e2, k), -np.ones(len(P)), -h]) / sigma_m

    sol = least_squares(residuals, np.zeros(6), jac=jacobian, loss="huber", f_scale=huber_k, method="trf",
                        x_scale=[0.01, 0.01, 0.005, 0.005, 0.005, 0.01], max_nfev=100)
    a, o, r, k = unpack(sol.x)
    return Cylinder(a, o, r), float(k)


def fit_cylinders_shared_radius(parts: list[tuple[np.ndarray, np.ndarray, list[CylinderView], Cylinder]],
                                intr: CameraIntrinsics, rng: np.random.Generator, *, threshold_m: float = 0.01,
                                radius_range_m: tuple[float, float] = (0.01, 0.25), sigma_3d_m: float = 0.003,
                                sigma_px: float = 1.0, lam: float = 1.0, huber_k: float = 1.345,
                                max_pixels_per_view: int = 400, edge_snap_px: int = 0) -> list[Cylinder]:
    """Eq. objectCylinderFB: one radius for a trunk's segments seen from several sides, each segment with
    its own axis and origin (each side's points and views are in that side's frame). parts: (points
    (N, 3), normals (N, 3), views, the side's own fit as the start)."""
    prepared = []
    for P, _, views, c0 in parts:
        P = np.asarray(P, float)
        P = P[np.abs(point_distance(P, c0)) < threshold_m]
        prepared.append((c0, P, [_prepare_view(v, intr, rng, max_pixels_per_view, edge_snap_px) for v in views]))
    cyls = _refine(prepared, intr, sigma_3d_m=sigma_3d_m, w2=np.sqrt(lam) / sigma_px, huber_k=huber_k)
    if not radius_range_m[0] <= cyls[0].radius <= radius_range_m[1]:
        raise CylinderError(f"two-side refinement left the radius range: r = {cyls[0].radius:.4f} m")
    return cyls


def fit_cylinder(points: np.ndarray, normals: np.ndarray, views: list[CylinderView], intr: CameraIntrinsics,
                 rng: np.random.Generator, *, up: np.ndarray, threshold_m: float = 0.01,
                 iterations: int = 200, max_axis_angle_deg: float = 30.0,
                 radius_range_m: tuple[float, float] = (0.01, 0.25), use_2d: bool = True,
                 sigma_3d_m: float = 0.003, sigma_px: float = 1.0, lam: float = 1.0, huber_k: float = 1.345,
                 max_pixels_per_view: int = 400, initial: Cylinder | None = None,
                 edge_snap_px: int = 0) -> CylinderFit:
    """RANSAC (two oriented points) then LM with Huber loss on eq. objectCylinder.

    points, normals (N, 3) in odom: the trunk segment's fused points; views: the frames that detected
    it (their depth pixels inside the mask and the mask's silhouette edges give the 2D terms; ignored
    when use_2d is False). `initial` skips RANSAC.
    """
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    up = np.asarray(up, float) / np.linalg.norm(up)
    if initial is None:
        found = ransac_cylinder(points, normals, rng, threshold_m=threshold_m, iterations=iterations, up=up,
                                max_axis_angle_deg=max_axis_angle_deg, radius_range_m=radius_range_m)
        if found is None:
            raise CylinderError(f"no cylinder found in {len(points)} points (RANSAC, {iterations} samples)")
        cyl0, inl = found
    else:
        cyl0 = initial
        inl = np.abs(point_distance(points, cyl0)) < threshold_m
    P = points[inl]  # (N_in, 3) 3D term: the RANSAC inliers
    data = [_prepare_view(v, intr, rng, max_pixels_per_view, edge_snap_px) for v in views] if use_2d else []
    cyl = _refine([(cyl0, P, data)], intr, sigma_3d_m=sigma_3d_m, w2=np.sqrt(lam) / sigma_px, huber_k=huber_k)[0]
    if not radius_range_m[0] <= cyl.radius <= radius_range_m[1]:
        raise CylinderError(f"cylinder refinement left the radius range: r = {cyl.radius:.4f} m")
    d3 = point_distance(points, cyl)
    inl_final = np.abs(d3) < threshold_m
    n2, rms2 = 0, float("nan")
    if data:
        r_px, r_edge = _StackedViews.of(data, intr).residuals(cyl, intr)
        r2c = np.concatenate([np.linalg.norm(r_px, axis=1), np.abs(r_edge)])
        n2, rms2 = len(r2c), float(np.sqrt(np.mean(r2c**2))) if len(r2c) else float("nan")
    return CylinderFit(cyl, int(inl_final.sum()), float(np.sqrt(np.mean(d3[inl_final] ** 2))) if inl_final.any()
                       else float("nan"), rms2, n2, bool(data))
