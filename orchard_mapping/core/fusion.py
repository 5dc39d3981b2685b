"""TSDF depth fusion and raw-depth cleaning (paper: first paragraph of "Trunk Modeling and
Local Ground Estimation").

Raw RGB-D depth in orchards is noisy, and depth edges between trunks, leaves and the
background produce "flying" pixels floating in the air. The paper fuses the depth of nearby
frames with the optimised poses into a TSDF (Curless & Levoy 1996), ray casts the fused depth
into each keyframe, ignores raw depth that differs largely from it, and removes floating
pixels that have no 3D neighbours within a distance threshold (Sotoodeh 2006).

Only what the caller needs is cleaned: `fuse_side`'s `select` may name a region of a keyframe (the
pipeline: the rows and columns around its trunk detections), and only its rays are cast and its pixels
cleaned, with a margin so that inside it the result is the whole frame's, pixel for pixel. On the front
side of the 10-tree standard row (59 keyframes with trunks, side by side in one process) that halved the
cleaning's time per keyframe: 81.6 -> 43.4 ms (ray casting 40.0 -> 12.1 ms median).

Frames and units: poses are T_odom_cam of the colour optical frame (x right, y down,
z forward), 4x4; depth is float32 metres along the optical axis (z), 0 = missing; colour
is RGB uint8. Points are in the odom frame.

Open3D notes (0.20, measured; docs/dependencies.md):
- `ScalableTSDFVolume` is broken (always empty); `t.geometry.VoxelBlockGrid` is used.
- `VoxelBlockGrid.ray_cast` returns depth biased 0.5-1 voxel too far (a flat wall at
  z = 1.2001..1.2091 m comes back 5.0..9.1 mm behind it with 1 cm voxels), while
  `extract_point_cloud` / `extract_triangle_mesh` are unbiased. `raycast_depth` therefore
  casts rays against the marching-cubes mesh of the grid with `RaycastingScene`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Literal

import cv2
import numpy as np
import open3d as o3d
import open3d.core as o3c
from scipy.spatial import cKDTree

from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import OrchardMappingError

__all__ = [
    "FusionError",
    "FusionResult",
    "TsdfFusion",
    "clean_depth",
    "fuse_side",
    "remove_floating_pixels",
]

# Defaults for an orchard row seen from ~1.25 m (trunks ~7 cm wide, thin leaves), RealSense-like
# depth noise sd ~ 0.004 z^2 (6 mm at 1.25 m, 16 mm at 2 m, 36 mm at 3 m):
# - 1 cm voxels put ~7 voxels across a trunk; the fused trunk points lie < 1 mm (median, radially)
#   off the true trunk. 5 mm voxels cost 2-3x the time and memory for little gain (median distance
#   of all fused points to the true surfaces 3.8 vs 4.1 mm in the same simulated row).
# - 4 cm truncation is ~6 noise sd at the trunk line and still ~1 sd at 3 m, and is
#   about a trunk's diameter: a wider band (6 cm) smears leaf edges into the air (3.6x more points
#   > 3 cm from any surface in the same test), a narrower one leaves holes in noisy far surfaces.
# - depth beyond 3 m (noise sd > 3.6 cm; the neighbouring rows ~4.6 m away) is not fused: fusing up
#   to 5-6 m cost ~10x the time per frame (5x the blocks) and barely helped the cleaning.
# - 8^3-voxel blocks (8 cm) fit the scattered leaves better than 16^3 blocks: fewer empty voxels
#   are touched per frame (59 vs 88 ms per 320x240 frame on 2 busy cores, same surfaces).
# - A voxel needs a weight (number of frames) >= 2 to be part of the surface: single-frame
#   noise and flying pixels do not survive, while a trunk seen in ~10 frames does.
DEFAULT_VOXEL_SIZE_M = 0.01
DEFAULT_SDF_TRUNC_M = 0.04
DEFAULT_DEPTH_MAX_M = 3.0
DEFAULT_BLOCK_RESOLUTION = 8
DEFAULT_BLOCK_COUNT = 4000  # initial hash-map capacity; it grows on demand (~10 KB per 8^3 block)
DEFAULT_MIN_WEIGHT = 2.0
DEFAULT_CLEAN_AFTER_M = 2.0
DEFAULT_CLEAN_BATCH_M = 4.0


class FusionError(OrchardMappingError):
    """Fusion input is unusable: wrong image shape or dtype, non-finite pose, ... (the message says which)."""


def _check_pose(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise FusionError(f"{what}: pose must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise FusionError(f"{what}: pose has non-finite entries")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise FusionError(f"{what}: pose rotation is not orthonormal")
    return T


def _check_depth(depth: np.ndarray, intr: CameraIntrinsics, what: str) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.shape != (intr.height, intr.width):
        raise FusionError(f"{what}: depth shape {depth.shape} != intrinsics (H, W) = ({intr.height}, {intr.width})")
    if not np.issubdtype(depth.dtype, np.floating):
        raise FusionError(f"{what}: depth must be float metres, got dtype {depth.dtype}")
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    # NaN / inf / negative depth means "missing", like 0.
    return np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0))


def _check_color(color: np.ndarray, intr: CameraIntrinsics, what: str) -> np.ndarray:
    color = np.asarray(color)
    if color.shape != (intr.height, intr.width, 3):
        raise FusionError(f"{what}: colour shape {color.shape} != ({intr.height}, {intr.width}, 3)")
    if color.dtype != np.uint8:
        raise FusionError(f"{what}: colour must be uint8 RGB, got dtype {color.dtype}")
    return color


def _near_any(points: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """(N,) bool: points (N, 3) within radius of any of centres (C, 3)."""
    if len(centres) == 0 or len(points) == 0:
        return np.zeros(len(points), bool)
    return cKDTree(centres).query(points, distance_upper_bound=radius)[0] <= radius


def _block_code(keys: np.ndarray) -> np.ndarray:
    """(N,) int64, one number per block coordinate (N, 3) (each within +-2^20 blocks, +-84 km at 8 cm)."""
    k = keys + (1 << 20)
    return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]


Region = tuple[int, int, int, int]  # (r0, c0, r1, c1) px: rows r0..r1-1, columns c0..c1-1 of an image


class TsdfFusion:
    """A TSDF volume (Open3D `VoxelBlockGrid` on the CPU) fed with posed RGB-D frames."""

    def __init__(self, intr: CameraIntrinsics, voxel_size_m: float = DEFAULT_VOXEL_SIZE_M,
                 sdf_trunc_m: float = DEFAULT_SDF_TRUNC_M, depth_max_m: float = DEFAULT_DEPTH_MAX_M,
                 block_resolution: int = DEFAULT_BLOCK_RESOLUTION, block_count: int = DEFAULT_BLOCK_COUNT,
                 min_weight: float = DEFAULT_MIN_WEIGHT) -> None:
        if not (voxel_size_m > 0 and sdf_trunc_m >= voxel_size_m and depth_max_m > 0):
            raise FusionError(f"need voxel_size_m > 0, sdf_trunc_m >= voxel_size_m and depth_max_m > 0; got "
                              f"{voxel_size_m}, {sdf_trunc_m}, {depth_max_m}")
        if intr.width <= 0 or intr.height <= 0 or intr.fx <= 0 or intr.fy <= 0:
            raise FusionError(f"invalid intrinsics {intr}")
        self.intr = intr
        self.voxel_size_m = float(voxel_size_m)
        self.sdf_trunc_m = float(sdf_trunc_m)
        self.depth_max_m = float(depth_max_m)
        self.min_weight = float(min_weight)
        self._trunc_mult = self.sdf_trunc_m / self.voxel_size_m  # Open3D states truncation in voxels
        self._K = o3c.Tensor(intr.K, o3c.float64)
        self._vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight", "color"), attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3)), voxel_size=self.voxel_size_m, block_resolution=int(block_resolution),
            block_count=int(block_count), device=o3c.Device("CPU:0"))
        self.block_m = self.voxel_size_m * int(block_resolution)  # m, edge of one block
        self._mesh_scene: o3d.t.geometry.RaycastingScene | None = None
        self._mesh_empty = False
        self._scene_near: tuple[bytes, o3d.t.geometry.RaycastingScene | None] | None = None  # (key, scene)
        self.frames_integrated = 0
        self.frames_empty = 0  # frames with no depth within depth_max_m: nothing fused
        self.blocks_retired = 0
        self.seconds_integrating = 0.0
        u, v = np.meshgrid(np.arange(intr.width, dtype=np.float32), np.arange(intr.height, dtype=np.float32))
        # (HW, 3) camera rays with z = 1, so a ray's hit distance is the optical-axis depth.
        self._rays_cam = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1).reshape(-1, 3)

    def integrate(self, depth_m: np.ndarray, color: np.ndarray, T_odom_cam: np.ndarray) -> None:
        """Fuse one frame: depth (H, W) float32 m (0 = missing), colour (H, W, 3) uint8 RGB, pose (4, 4)."""
        what = f"frame {self.frames_integrated}"
        depth = _check_depth(depth_m, self.intr, what)
        color = _check_color(color, self.intr, what)
        T = _check_pose(T_odom_cam, what)
        t0 = time.perf_counter()
        extrinsic = o3c.Tensor(np.linalg.inv(T), o3c.float64)  # T_cam_odom
        d_img = o3d.t.geometry.Image(o3c.Tensor(depth))
        # Open3D accepts float depth only with float colour; colour is stored in [0, 1].
        c_img = o3d.t.geometry.Image(o3c.Tensor(color.astype(np.float32) * np.float32(1.0 / 255.0)))
        # A frame with nothing within reach (a gap between trees, open ground at a row's end) fuses nothing.
        # Open3D aborts a frame that touches no block, also when its few pixels in reach fall between the
        # ones it samples (seen on a simulated row), so its own verdict counts too.
        blocks = None
        if np.any((depth > 0) & (depth <= self.depth_max_m)):
            try:
                blocks = self._vbg.compute_unique_block_coordinates(d_img, self._K, extrinsic, 1.0,
                                                                    self.depth_max_m, self._trunc_mult)
            except RuntimeError as err:
                if "No block is touched" not in str(err):
                    raise
        if blocks is None:
            self.frames_empty += 1
            return
        self._vbg.integrate(blocks, d_img, c_img, self._K, extrinsic, 1.0, self.depth_max_m, self._trunc_mult)
        self.seconds_integrating += time.perf_counter() - t0
        self.frames_integrated += 1
        self._surface_changed()

    def extract_point_cloud(self, weight_threshold: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Surface points (P, 3) float32 m in odom and their colours (P, 3) uint8 RGB.

        weight_threshold: minimum number of frames (weight) a voxel needs; None = `min_weight`.
        """
        w = self.min_weight if weight_threshold is None else float(weight_threshold)
        if self._vbg.hashmap().size() == 0:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        pcd = self._vbg.extract_point_cloud(w)
        if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        pts = pcd.point.positions.numpy().astype(np.float32)  # (P, 3)
        cols = np.clip(pcd.point.colors.numpy() * 255.0 + 0.5, 0, 255).astype(np.uint8)  # (P, 3)
        # Open3D extracts in parallel, in an order that changes from run to run (the same points): sorted, the
        # same bag gives the same cloud, and so the same trunks (RANSAC draws points by index)
        order = np.lexsort((pts[:, 2], pts[:, 1], pts[:, 0]))
        return pts[order], cols[order]

    def _surface_changed(self) -> None:
        self._mesh_scene = None  # re-extract on the next ray cast
        self._mesh_empty = False
        self._scene_near = None

    def _build_scene(self, centres: np.ndarray | None) -> o3d.t.geometry.RaycastingScene | None:
        """A ray-casting scene of the fused surface (only the triangles with a vertex within depth_max + sdf_trunc
        of the camera centres (C, 3) m, odom, if given); None when there is no surface."""
        mesh = self._vbg.extract_triangle_mesh(self.min_weight) if self._vbg.hashmap().size() else None
        if mesh is None or mesh.triangle.indices.shape[0] == 0:
            return None
        v = mesh.vertex.positions.numpy().astype(np.float32)  # (V, 3)
        tri = mesh.triangle.indices.numpy()  # (T, 3)
        if centres is not None:
            tri = tri[_near_any(v, centres, self.depth_max_m + self.sdf_trunc_m)[tri].any(axis=1)]
            if not len(tri):
                return None
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3c.Tensor(v), o3c.Tensor(np.ascontiguousarray(tri, np.uint32)))
        return scene

    def _scene(self) -> o3d.t.geometry.RaycastingScene | None:
        if self._mesh_scene is None and not self._mesh_empty:
            self._mesh_scene = self._build_scene(None)
            self._mesh_empty = self._mesh_scene is None
        return self._mesh_scene

    def focus(self, centres: np.ndarray | None) -> None:
        """Ray casts until the next change see only the surface within depth_max + sdf_trunc of these camera
        centres (C, 3) m, odom (None: all of it). Building the ray-casting index costs ~0.08 s per metre of
        row (measured on a 30-tree row): a few metres around the cameras cost less than the whole volume."""
        if centres is None:
            self._scene_near = None
            return
        c = np.asarray(centres, np.float32).reshape(-1, 3)
        if self._scene_near is not None and self._scene_near[0] == c.tobytes():
            return
        self._scene_near = (c.tobytes(), self._build_scene(c))

    def retire_blocks(self, keep: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Free the blocks whose centres are farther than radius_m from every point of keep (C, 3) m, odom,
        and return their surface points (P, 3) float32 and colours (P, 3) uint8 (as `extract_point_cloud`).

        Nothing integrated later may reach a freed block (the caller keeps every camera that may still
        see it), so its surface is final. A freed block's buffer slot is zeroed: Open3D reuses the slot
        for the next new block without clearing it (measured: stale TSDF and weight came back)."""
        hm = self._vbg.hashmap()
        if hm.size() == 0:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        buf = hm.active_buf_indices().to(o3c.int64)  # (B,)
        keys = hm.key_tensor()[buf].numpy()  # (B, 3) int32 block coordinates
        far = ~_near_any((keys + 0.5) * self.block_m, np.asarray(keep, float).reshape(-1, 3), radius_m)  # (B,)
        if not far.any():
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        pts, cols = self.extract_point_cloud()
        pk = np.floor(pts / self.block_m).astype(np.int64)  # (P, 3) block of each point
        sel = np.isin(_block_code(pk), _block_code(keys[far].astype(np.int64)))
        idx = buf.numpy()[far]
        for name in ("tsdf", "weight", "color"):
            self._vbg.attribute(name).numpy()[idx] = 0.0  # a numpy view of the grid's buffer
        hm.erase(o3c.Tensor(np.ascontiguousarray(keys[far])))
        self.blocks_retired += int(far.sum())
        self._surface_changed()
        return pts[sel], cols[sel]

    @property
    def n_blocks(self) -> int:
        return int(self._vbg.hashmap().size())

    def raycast_depth(self, T_odom_cam: np.ndarray, region: Region | None = None) -> np.ndarray:
        """Fused depth (H, W) float32 m seen from pose T_odom_cam; 0 where no fused surface (or beyond depth_max).
        With a region (r0, c0, r1, c1) px, only its pixels: (r1 - r0, c1 - c0)."""
        T = _check_pose(T_odom_cam, "raycast")
        r0, c0, r1, c1 = (0, 0, self.intr.height, self.intr.width) if region is None else region
        H, W = r1 - r0, c1 - c0
        scene = self._scene() if self._scene_near is None else self._scene_near[1]
        if scene is None:
            return np.zeros((H, W), np.float32)
        rays = self._rays_cam.reshape(self.intr.height, self.intr.width, 3)[r0:r1, c0:c1].reshape(-1, 3)
        dirs = rays @ T[:3, :3].T.astype(np.float32)  # (HW, 3) in odom
        origin = np.broadcast_to(T[:3, 3].astype(np.float32), dirs.shape)
        t_hit = scene.cast_rays(o3c.Tensor(np.ascontiguousarray(np.hstack([origin, dirs]))))["t_hit"].numpy()
        ok = np.isfinite(t_hit) & (t_hit <= self.depth_max_m)
        return np.where(ok, t_hit, 0.0).astype(np.float32).reshape(H, W)

    @property
    def ms_per_frame(self) -> float:
        return 1000.0 * self.seconds_integrating / max(1, self.frames_integrated)


# Cleaning tolerances. A raw pixel is dropped when it differs from the fused depth by more than
# max(abs_tol_m, rel_tol * z): ~3 noise sd (0.004 z^2) up to ~1.5 m, then the relative term (which
# grows slower than the noise) lets some far noise through rather than punching holes in the ground.
# rel_tol 0.03 -> 0.02 measured on 4 seeds (test_fusion.py, within 2 m): bad pixels kept by clean_depth
# 17-22 % -> 13-18 %, good pixels dropped 1.1-1.3 % -> 2.2-2.5 %.
DEFAULT_REL_TOL = 0.02
DEFAULT_ABS_TOL_M = 0.03
MIXED_PIXEL_GAP_M = 0.15  # m, near-far spread of a 3x3 window that makes it a depth jump (see clean_depth)
# The ray-cast fused surface of a 7 cm trunk comes out up to ~1 voxel narrower than the trunk (the fused
# points themselves lie on it, < 1 mm radially): raw pixels may also agree with the nearest fused depth
# within this lateral distance (converted to pixels at 1 m depth; 5 px at 320x240, 10 px at 640x480).
DEFAULT_SILHOUETTE_TOL_M = 0.015
# Floating pixels: a pixel needs `min_neighbours` 3D points among its 5x5 image neighbours within
# radius_m + 3 sqrt(2) noise_coeff z^2 (3 sd of the difference of two independent noisy depths). On the
# simulated row (320x240) 1 cm / 5 neighbours removed more flying pixels than 2 cm / 3 neighbours
# (bad pixels x6.5 vs x3.5 fewer after cleaning) for 1 % more good pixels lost (mostly leaf edges).
DEFAULT_FLOAT_RADIUS_M = 0.01
DEFAULT_FLOAT_MIN_NEIGHBOURS = 5
DEFAULT_FLOAT_WINDOW = 5
DEFAULT_DEPTH_NOISE_COEFF = 0.004  # sd = coeff * z^2 (m), RealSense D4xx-like


def clean_depth(raw: np.ndarray, fused: np.ndarray, *, rel_tol: float = DEFAULT_REL_TOL,
                abs_tol_m: float = DEFAULT_ABS_TOL_M, window_px: int = 0, keep_unverified: bool = True) -> np.ndarray:
    """Raw depth (H, W) m with pixels that differ largely from the fused depth (H, W) m set to 0.

    A raw pixel agrees with a fused depth f when |raw - f| <= max(abs_tol_m, rel_tol * f). It is
    kept when it agrees with the fused depth at the pixel, or (window_px > 0) with the nearest fused
    depth within window_px pixels: the fused surface of a thin object (a trunk) is ray cast up to about
    a voxel narrower than it is, so true raw pixels along its silhouette would otherwise be taken for
    flying pixels; a flying pixel lies between the foreground and the background and agrees with
    neither. Where the fused depth is 0 (nothing fused along the ray: mostly thin leaves the TSDF lost)
    the raw value cannot be checked against it: it is dropped unless keep_unverified, and with
    keep_unverified it is still dropped when it is a mixed pixel at a depth jump (its 3x3 window spans
    more than MIXED_PIXEL_GAP_M and it agrees with neither the nearest nor the farthest depth there).
    Measured (test_fusion.py, 4 seeds, fuse_side's cleaning within 2 m): bad-pixel share lowered
    5.8-6.2x (4.7-5.3x without the mixed-pixel test) for 5.1-5.3 % of good pixels dropped (3.7-3.9 %).
    """
    raw = np.asarray(raw)
    fused = np.asarray(fused)
    if raw.ndim != 2 or raw.shape != fused.shape:
        raise FusionError(f"clean_depth: raw {raw.shape} and fused {fused.shape} must be equal (H, W) images")
    if rel_tol < 0 or abs_tol_m < 0 or window_px < 0:
        raise FusionError(f"clean_depth: tolerances and window must be >= 0, got rel_tol={rel_tol}, "
                          f"abs_tol_m={abs_tol_m}, window_px={window_px}")
    raw32 = np.where(np.isfinite(raw) & (raw > 0), raw, 0.0).astype(np.float32)
    f = np.where(np.isfinite(fused) & (fused > 0), fused, 0.0).astype(np.float32)

    def agrees(ref: np.ndarray) -> np.ndarray:  # (H, W) bool
        tol = np.maximum(np.float32(abs_tol_m), np.float32(rel_tol) * ref)
        return (ref > 0) & (np.abs(raw32 - ref) <= tol)

    ok = agrees(f)
    if window_px > 0:
        # Nearest fused depth in the window: a min filter with "nothing fused" as +inf.
        far = np.float32(1e6)
        kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * window_px + 1, 2 * window_px + 1))
        f_near = cv2.erode(np.where(f > 0, f, far), kernel, borderType=cv2.BORDER_REPLICATE)
        ok |= agrees(np.where(f_near < far, f_near, np.float32(0.0)))
    bad = (f > 0) & ~ok
    if not keep_unverified:
        bad |= f <= 0
    else:
        # Where nothing was fused (mostly thin leaves the TSDF lost) the fused depth cannot judge a pixel; a
        # mixed pixel there still shows itself: it lies between the near and far surfaces of its 3x3
        # neighbourhood and agrees with neither.
        kernel3 = np.ones((3, 3), np.uint8)
        near = cv2.erode(np.where(raw32 > 0, raw32, np.float32(1e6)), kernel3, borderType=cv2.BORDER_REPLICATE)
        far_ = cv2.dilate(raw32, kernel3, borderType=cv2.BORDER_REPLICATE)
        gap = far_ - near
        # A jump, not a slope: a grazing surface changes a few cm per pixel, a silhouette tens of cm.
        tol = np.maximum(np.maximum(np.float32(abs_tol_m), np.float32(rel_tol) * raw32), np.float32(0.25) * gap)
        mixed = (gap > np.float32(MIXED_PIXEL_GAP_M)) & (raw32 - near > tol) & (far_ - raw32 > tol)
        bad |= (f <= 0) & (raw32 > 0) & mixed
    return np.where(bad, np.float32(0.0), raw32)


def remove_floating_pixels(depth: np.ndarray, intr: CameraIntrinsics, *, radius_m: float = DEFAULT_FLOAT_RADIUS_M,
                           min_neighbours: int = DEFAULT_FLOAT_MIN_NEIGHBOURS, window: int = DEFAULT_FLOAT_WINDOW,
                           depth_noise_coeff: float = DEFAULT_DEPTH_NOISE_COEFF) -> np.ndarray:
    """Depth (H, W) m with pixels removed (set to 0) that have fewer than `min_neighbours` 3D points nearby.

    Neighbours are searched among the pixels of a `window` x `window` image neighbourhood (the
    back-projected points nearest in the image are the candidates nearest in space); a neighbour counts
    when it lies within radius_m + 3 sqrt(2) depth_noise_coeff z^2 of the pixel's 3D point (the radius
    grows with the depth noise so that a noisy far surface is not taken for floating points).
    Vectorised: one pass over the window offsets, whole images at a time.
    """
    depth = _check_depth(depth, intr, "remove_floating_pixels")
    if window < 3 or window % 2 == 0:
        raise FusionError(f"remove_floating_pixels: window must be odd and >= 3, got {window}")
    if min_neighbours < 1 or min_neighbours > window * window - 1:
        raise FusionError(f"remove_floating_pixels: min_neighbours must be in 1..{window * window - 1}")
    H, W = depth.shape
    r = window // 2
    u = (np.arange(W, dtype=np.float32) - np.float32(intr.cx)) / np.float32(intr.fx)  # (W,)
    v = (np.arange(H, dtype=np.float32) - np.float32(intr.cy)) / np.float32(intr.fy)  # (H,)
    z = depth
    valid = z > 0
    thresh = np.float32(radius_m) + np.float32(3.0 * np.sqrt(2.0) * depth_noise_coeff) * z * z  # (H, W) m
    thresh2 = thresh * thresh
    # One padded (H + 2r, W + 2r) float32 plane per coordinate (camera frame): per offset the squared
    # distance is three in-place subtract/square/add passes (3x faster than an (H, W, 3) einsum).
    planes = [np.pad(c, r) for c in (u[None, :] * z, v[:, None] * z, z)]
    centre = [c[r:r + H, r:r + W] for c in planes]
    pad_v = np.pad(valid, r)
    count = np.zeros((H, W), np.int16)
    d2 = np.empty((H, W), np.float32)
    tmp = np.empty((H, W), np.float32)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx == 0:
                continue
            d2.fill(0.0)
            for c, p in zip(planes, centre, strict=True):
                np.subtract(c[r + dy:r + dy + H, r + dx:r + dx + W], p, out=tmp)
                np.multiply(tmp, tmp, out=tmp)
                d2 += tmp
            count += pad_v[r + dy:r + dy + H, r + dx:r + dx + W] & (d2 <= thresh2)
    keep = valid & (count >= min_neighbours)
    return np.where(keep, z, np.float32(0.0))


@dataclass(frozen=True)
class FusionResult:
    """One side's fused cloud and the cleaned depth of its keyframes."""

    points: np.ndarray  # (P, 3) float32 m, odom
    colors: np.ndarray  # (P, 3) uint8 RGB
    cleaned_depth: dict[int, np.ndarray]  # keyframe index (position in the input frames) -> (H, W) float32 m, 0 = removed
    seconds_per_frame: float  # s, mean TSDF integration time per integrated frame
    seconds_total: float  # s, the whole call
    mode: str  # "side" (one grid for the side) or "local" (a grid of the nearest frames per keyframe)
    # same keys: (H, W, 3) uint8 RGB, the trunk detector's input; only with keep_color (else empty)
    cleaned_color: dict[int, np.ndarray] = field(default_factory=dict)
    peak_blocks: int = 0  # the most voxel blocks the volume held at once (~10 KB each)
    blocks_retired: int = 0  # blocks extracted into the cloud and freed as the volume moved on


def _nearest_frames(centres: np.ndarray, k: int, n: int) -> np.ndarray:
    """Indices (n_k,) of the n frames whose camera centres (F, 3) are nearest to frame k's (k included)."""
    d = np.linalg.norm(centres - centres[k], axis=1)
    order = np.lexsort((np.abs(np.arange(len(centres)) - k), d))  # nearest first, ties by time
    return np.sort(order[:n])


@dataclass(frozen=True)
class FusionParams:
    """Settings of `fuse_side` (config section `fusion`), passed as keywords."""

    __pydantic_config__ = {"extra": "forbid"}  # config files: unknown keys are errors

    mode: Literal["side", "local"] = "side"  # fused depth from the whole side's grid, or the paper's nearest frames
    neighbours: int = 10  # frames per local grid (mode "local")
    voxel_size_m: float = DEFAULT_VOXEL_SIZE_M
    sdf_trunc_m: float = DEFAULT_SDF_TRUNC_M
    depth_max_m: float = DEFAULT_DEPTH_MAX_M
    min_weight: float = DEFAULT_MIN_WEIGHT
    rel_tol: float = DEFAULT_REL_TOL
    abs_tol_m: float = DEFAULT_ABS_TOL_M
    silhouette_tol_m: float = DEFAULT_SILHOUETTE_TOL_M
    float_radius_m: float = DEFAULT_FLOAT_RADIUS_M
    float_min_neighbours: int = DEFAULT_FLOAT_MIN_NEIGHBOURS
    # m: the front end's keyframes are ~2.5 cm apart (for BA); fusing and cleaning each would make fusion
    # the slowest stage (TSDF integration ~0.1 s per frame at 1 cm voxels up to 3 m, cleaning ~0.2 s
    # on 2 cores). Frames nearer than fused_spacing_m to the last integrated one are skipped (a surface
    # point at 1.25 m is still fused from ~17 views per sweep), and depth is cleaned only for keyframes
    # cleaned_spacing_m apart.
    fused_spacing_m: float = 0.1
    cleaned_spacing_m: float = 0.15
    # m: a keyframe's depth is cleaned once the camera is this far past it, against the surface fused so far
    # (frames farther ahead see only the far ground of its view), in batches clean_batch_m long: each batch
    # extracts the volume's mesh once (~0.05 s per metre of volume) and indexes the part near its keyframes.
    clean_after_m: float = DEFAULT_CLEAN_AFTER_M
    clean_batch_m: float = DEFAULT_CLEAN_BATCH_M


# Called with (keyframe position, cleaned depth (H, W) float32 m, colour (H, W, 3) uint8 or None) as soon as a
# keyframe's depth is cleaned, so the caller can use it and let it go (the streaming pipeline).
OnCleaned = Callable[[int, np.ndarray, "np.ndarray | None"], None]
# Called with (keyframe position, colour (H, W, 3) uint8, raw depth) as a keyframe comes due for cleaning:
# False skips it, True cleans the whole frame, a Region (r0, c0, r1, c1) px cleans only that part.
Select = Callable[[int, np.ndarray, np.ndarray], "bool | Region"]


def fuse_side(frames: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]], intr: CameraIntrinsics, *,
              keyframes: Iterable[int] | None = None, neighbours: int = 10, mode: Literal["side", "local"] = "side",
              voxel_size_m: float = DEFAULT_VOXEL_SIZE_M, sdf_trunc_m: float = DEFAULT_SDF_TRUNC_M,
              depth_max_m: float = DEFAULT_DEPTH_MAX_M, min_weight: float = DEFAULT_MIN_WEIGHT,
              rel_tol: float = DEFAULT_REL_TOL, abs_tol_m: float = DEFAULT_ABS_TOL_M,
              silhouette_tol_m: float = DEFAULT_SILHOUETTE_TOL_M, float_radius_m: float = DEFAULT_FLOAT_RADIUS_M,
              float_min_neighbours: int = DEFAULT_FLOAT_MIN_NEIGHBOURS, fused_spacing_m: float = 0.0,
              cleaned_spacing_m: float = 0.0, clean_after_m: float = DEFAULT_CLEAN_AFTER_M,
              clean_batch_m: float = DEFAULT_CLEAN_BATCH_M, keep_color: bool = False,
              on_cleaned: OnCleaned | None = None, select: Select | None = None) -> FusionResult:
    """Fuse one side's frames (depth (H, W) m, colour (H, W, 3) uint8, T_odom_cam (4, 4)) and clean keyframe depth.

    The frames go into one TSDF volume, whose surface is the side's cloud. The cleaned depth of a
    keyframe is its raw depth checked against fused depth ray cast into it (`clean_depth`, with a
    lateral tolerance of silhouette_tol_m at 1 m), then freed of floating pixels
    (`remove_floating_pixels`); raw depth beyond depth_max_m is dropped (not fused, so not checked).
    The fused depth comes from
      mode="side":  the side's volume (one integration per frame; the default). The volume moves with
                    the camera: a keyframe is cleaned once the camera is clean_after_m past it (in batches
                    clean_batch_m long), and blocks out of reach of the camera and of every keyframe not
                    yet cleaned are extracted into the cloud and freed. Memory does not grow with the row.
      mode="local": as in the paper, a grid of the keyframe's `neighbours` nearest frames (by camera
                    centre) per keyframe: `neighbours` integrations per keyframe (keeps every frame).
    keyframes: positions in `frames` to clean (None = every frame); of these only those at least
    cleaned_spacing_m (camera centres) after the previous cleaned one are cleaned (0 = all; not applied
    with a `select`, which is asked about every one of them).
    fused_spacing_m: frames nearer than this to the last integrated one are not integrated (0 = all).
    keep_color: also keep the colour image of every cleaned keyframe (for the trunk detector; ~1 MB each).
    on_cleaned: when given, each cleaned keyframe is handed to it (in order) instead of being kept in
    the result (cleaned_depth and cleaned_color come back empty).
    select: when given, called with (position, colour, raw depth) as each keyframe comes due for cleaning; a keyframe
    it refuses is not cleaned (the pipeline cleans only the keyframes with a trunk detection in them).
    """
    t_start = time.perf_counter()
    window_px = int(np.ceil(silhouette_tol_m * max(intr.fx, intr.fy) / 1.0))  # px at 1 m depth
    if mode not in ("side", "local"):
        raise FusionError(f"fuse_side: mode must be 'side' or 'local', got {mode!r}")
    if neighbours < 1:
        raise FusionError(f"fuse_side: neighbours must be >= 1, got {neighbours}")
    if not (clean_after_m >= 0 and clean_batch_m > 0):
        raise FusionError(f"fuse_side: need clean_after_m >= 0 and clean_batch_m > 0, got {clean_after_m}, "
                          f"{clean_batch_m}")

    def new_grid() -> TsdfFusion:
        return TsdfFusion(intr, voxel_size_m=voxel_size_m, sdf_trunc_m=sdf_trunc_m, depth_max_m=depth_max_m,
                          min_weight=min_weight)

    side = new_grid()
    # m: a block this far from a camera cannot be touched by its depth (nor hold surface it sees)
    reach = depth_max_m + sdf_trunc_m + side.block_m * np.sqrt(3.0)
    key_set = None if keyframes is None else set(int(k) for k in keyframes)
    kept: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # frames held for local grids
    # keyframes to clean: (i, raw, colour, T, region to clean or None for the whole frame)
    pending: list[tuple[int, np.ndarray, np.ndarray | None, np.ndarray, Region | None]] = []
    cleaned: dict[int, np.ndarray] = {}
    color_key: dict[int, np.ndarray] = {}  # keyframe -> its colour image (keep_color)
    chunks: list[tuple[np.ndarray, np.ndarray]] = []  # the cloud, extracted as the volume moves on
    poses: list[np.ndarray] = []  # (4, 4) per frame, mode "local" only
    seconds = 0.0
    frames_done = 0
    peak = [0]  # the most blocks held at once
    last_retired: list[np.ndarray | None] = [None]  # camera centre at the last retirement of blocks

    def emit(k: int, depth: np.ndarray, color: np.ndarray | None) -> None:
        if on_cleaned is not None:
            on_cleaned(k, depth, color)
            return
        cleaned[k] = depth
        if color is not None:
            color_key[k] = color

    # px around a region that its cleaning reads: the nearest-fused-depth window, then the floating-pixel
    # window over the cleaned pixels (and the mixed-pixel test's 3x3): inside the region the result equals
    # the whole frame's.
    region_margin = window_px + DEFAULT_FLOAT_WINDOW // 2 + 2

    def clean(k: int, raw: np.ndarray, color: np.ndarray | None, T: np.ndarray, region: Region | None) -> None:
        if region is None:
            r0, c0, r1, c1 = 0, 0, intr.height, intr.width
        else:
            r0, c0 = max(0, region[0] - region_margin), max(0, region[1] - region_margin)
            r1, c1 = min(intr.height, region[2] + region_margin), min(intr.width, region[3] + region_margin)
        cut = replace(intr, width=c1 - c0, height=r1 - r0, cx=intr.cx - c0, cy=intr.cy - r0)
        fused = side.raycast_depth(T, (r0, c0, r1, c1)) if mode == "side" else local_fused(k, T)[r0:r1, c0:c1]
        d = raw[r0:r1, c0:c1]
        d = np.where(d <= depth_max_m, d, np.float32(0.0))
        d = clean_depth(d, fused, rel_tol=rel_tol, abs_tol_m=abs_tol_m, window_px=window_px)
        d = remove_floating_pixels(d, cut, radius_m=float_radius_m, min_neighbours=float_min_neighbours)
        if region is not None:  # the region alone is cleaned; the rest of the frame is left out (0)
            out = np.zeros(raw.shape, np.float32)
            q0, p0 = max(0, region[0]), max(0, region[1])
            q1, p1 = min(intr.height, region[2]), min(intr.width, region[3])
            out[q0:q1, p0:p1] = d[q0 - r0:q1 - r0, p0 - c0:p1 - c0]
            d = out
        emit(k, d, color)

    def flush(here: np.ndarray | None) -> None:
        """Clean the keyframes clean_after_m behind `here` (all of them at the end: None), then free the blocks
        no camera still needs."""
        ready = [p for p in pending if here is None or np.linalg.norm(p[3][:3, 3] - here) >= clean_after_m]
        if ready:
            side.focus(np.array([p[3][:3, 3] for p in ready]))
            for k, raw, color, T, region in ready:
                clean(k, raw, color, T, region)
            side.focus(None)
            del pending[:len(ready)]
        if here is not None:
            retire(here)

    def retire(here: np.ndarray) -> None:
        peak[0] = max(peak[0], side.n_blocks)
        keep = np.array([here] + [p[3][:3, 3] for p in pending])
        chunks.append(side.retire_blocks(keep, reach))
        last_retired[0] = here

    last_cleaned: np.ndarray | None = None  # camera centre of the last frame kept for cleaning
    n = 0
    last_fused: np.ndarray | None = None  # camera centre of the last frame integrated into the side grid
    for i, (depth, color, T) in enumerate(frames):
        Tc = _check_pose(T, f"frame {i}")
        here = Tc[:3, 3]
        if last_fused is None or np.linalg.norm(here - last_fused) >= fused_spacing_m:
            side.integrate(depth, color, Tc)
            last_fused = here
        d = _check_depth(depth, intr, f"frame {i}")
        if last_retired[0] is None:
            last_retired[0] = here
        if mode == "local":
            poses.append(Tc)  # the nearest frames of each keyframe are chosen from all of them
        # with a `select`, every keyframe is offered to it: it has its own spacing (the pipeline's detector frames,
        # trunks.detect_every_m on by the front end's poses). Thinned here as well, by these poses, the two
        # spacings fell out of step: on the back side of a simulated slope_weeds row no detector frame reached
        # `select` over the first 5 m, and 4 of its 10 trunks were lost.
        if (key_set is None or i in key_set) and (select is not None or last_cleaned is None
                                                  or np.linalg.norm(here - last_cleaned) >= cleaned_spacing_m):
            last_cleaned = here
            chosen = True if select is None else select(i, np.asarray(color), d)
            if chosen is not False:
                region = None if chosen is True else tuple(int(x) for x in chosen)
                pending.append((i, d, np.asarray(color) if keep_color else None, Tc, region))
        if mode == "local":
            kept.append((d, np.asarray(color), Tc))
        elif pending and np.linalg.norm(pending[0][3][:3, 3] - here) >= clean_after_m + clean_batch_m:
            flush(here)
        elif not pending and np.linalg.norm(here - last_retired[0]) >= clean_batch_m:
            # nothing to clean for a while (no trunk in view): the volume must move on all the same, else it
            # grows over the whole stretch (a 100-tree side peaked at 3.6 GB in fusion before this)
            retire(here)
        n = i + 1
    if key_set is not None and (missing := sorted(k for k in key_set if not 0 <= k < n)):
        raise FusionError(f"fuse_side: keyframes {missing[:5]} out of range 0..{n - 1}")
    if mode == "side":
        flush(None)
    peak[0] = max(peak[0], side.n_blocks)
    chunks.append(side.extract_point_cloud())
    points = np.concatenate([c[0] for c in chunks])
    colors = np.concatenate([c[1] for c in chunks])
    seconds += side.seconds_integrating
    frames_done += side.frames_integrated
    if mode == "local":
        centres = np.array([T[:3, 3] for T in poses]) if poses else np.zeros((0, 3))

        def local_fused(k: int, T: np.ndarray) -> np.ndarray:
            nonlocal seconds, frames_done
            local = new_grid()
            for j in _nearest_frames(centres, k, neighbours):
                local.integrate(*kept[j])
            seconds += local.seconds_integrating
            frames_done += local.frames_integrated
            return local.raycast_depth(T)

        for k, raw, color, T, region in pending:
            clean(k, raw, color, T, region)
    return FusionResult(points, colors, cleaned, seconds / max(1, frames_done), time.perf_counter() - t_start, mode,
                        color_key, peak_blocks=peak[0], blocks_retired=side.blocks_retired)
