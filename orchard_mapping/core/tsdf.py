"""The TSDF volume of depth fusion (paper: first paragraph of "Trunk Modeling and Local Ground Estimation";
Curless & Levoy 1996): posed RGB-D frames integrated into an Open3D `VoxelBlockGrid`, its surface extracted
as points or a mesh, fused depth ray cast into a keyframe (against the mesh: module docstring of core.fusion,
"Open3D notes"), and blocks behind the camera retired as it moves on.

Frames and units: poses are T_odom_cam of the colour optical frame (x right, y down, z forward), 4x4; depth
is float32 metres along the optical axis, 0 = missing; colour RGB uint8; points in the odom frame.
"""

from __future__ import annotations

import time

import numpy as np
import open3d as o3d
import open3d.core as o3c
from scipy.spatial import cKDTree

from orchard_mapping.core.depth_cleaning import FusionError, check_color, check_depth, check_pose
from orchard_mapping.core.types import CameraIntrinsics

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
        depth = check_depth(depth_m, self.intr, what)
        color = check_color(color, self.intr, what)
        T = check_pose(T_odom_cam, what)
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
        T = check_pose(T_odom_cam, "raycast")
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
