"""RGB-D rendering of a Scene with Open3D's RaycastingScene, plus a RealSense-like sensor model.

One ray per pixel through the colour camera's pinhole (no distortion); depth is
aligned to colour by construction. Colour comes from per-triangle albedo,
procedural 3D textures evaluated at the surface's rest position (so texture
stays on leaves that move in wind) and Lambertian shading under a fixed sun.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.sim.scene import Cls, Scene

_SUN = np.array([0.35, -0.45, 0.82])
_SUN /= np.linalg.norm(_SUN)


class ValueNoise3D:
    """Smooth 3D value noise from a periodic random lattice (vectorised, deterministic)."""

    def __init__(self, seed: int, size: int = 32) -> None:
        self.size = size
        self.flat = np.random.default_rng(seed).random(size ** 3).astype(np.float32)

    def __call__(self, p: np.ndarray) -> np.ndarray:  # p (N, 3) float32 lattice units -> (N,) in [0, 1]
        f = np.floor(p)
        r = p - f
        r = r * r * (3 - 2 * r)
        s = self.size
        i = f.astype(np.int32) & (s - 1)  # size is a power of two: & wraps negatives too
        j = (i + 1) & (s - 1)
        ix = (i[:, 0] * s * s, j[:, 0] * s * s)
        iy = (i[:, 1] * s, j[:, 1] * s)
        iz = (i[:, 2], j[:, 2])
        wx = (1 - r[:, 0], r[:, 0])
        wy = (1 - r[:, 1], r[:, 1])
        wz = (1 - r[:, 2], r[:, 2])
        out = np.zeros(len(p), np.float32)
        for a in (0, 1):
            for b in (0, 1):
                base = ix[a] + iy[b]
                wab = wx[a] * wy[b]
                out += wab * (wz[0] * self.flat[base + iz[0]] + wz[1] * self.flat[base + iz[1]])
        return out

    def fbm(self, p: np.ndarray, octaves: int = 2) -> np.ndarray:
        out = np.zeros(len(p), np.float32)
        amp, total = 1.0, 0.0
        for o in range(octaves):
            out += amp * self(p * np.float32(2.0 ** o) + np.float32(17.0 * o))
            total += amp
            amp *= 0.5
        return out / np.float32(total)


@dataclass(frozen=True)
class RenderOutput:
    depth: np.ndarray  # (H, W) float32 metres along the optical axis, 0 = no surface (sky)
    color: np.ndarray  # (H, W, 3) uint8 RGB, noise-free
    cls: np.ndarray  # (H, W) uint8 Cls
    inst: np.ndarray  # (H, W) int32 instance (tree id / fruit index / post index), -1 else
    tri: np.ndarray  # (H, W) int64 triangle index, -1 = sky
    points: np.ndarray  # (H, W, 3) float32 world hit points (rest position), 0 for sky


class Renderer:
    def __init__(self, scene: Scene, intrinsics: CameraIntrinsics, seed: int) -> None:
        self.scene = scene
        self.K = intrinsics
        self.noise = ValueNoise3D(seed + 101)
        self._static: o3d.t.geometry.RaycastingScene | None = None
        self._vertices32 = scene.vertices.astype(np.float32)
        self._tri_ext = np.vstack([scene.triangles, [[0, 0, 0]]])
        self._cls_ext = np.append(scene.tri_cls, np.uint8(Cls.SKY))
        self._inst_ext = np.append(scene.tri_inst, np.int32(-1))
        self._albedo_ext = np.vstack([scene.tri_albedo, np.zeros((1, 3), np.float32)])
        u, v = np.meshgrid(np.arange(intrinsics.width, dtype=np.float32),
                           np.arange(intrinsics.height, dtype=np.float32))
        self._dirs_cam = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy,
                                   np.ones_like(u)], -1).reshape(-1, 3)  # (HW, 3), z = 1 so t_hit = depth

    def _raycaster(self, vertices: np.ndarray) -> o3d.t.geometry.RaycastingScene:
        rc = o3d.t.geometry.RaycastingScene()
        rc.add_triangles(vertices.astype(np.float32), self.scene.triangles.astype(np.uint32))
        return rc

    def vertices_at(self, t: float) -> np.ndarray | None:
        """Vertex positions at time t (s) under wind, or None when the scene is static."""
        w = self.scene.scenario.wind
        if not w.enabled:
            return None
        sc = self.scene
        ph = 2 * np.pi * w.frequency_hz * t + sc.vertex_phase
        # Leaves flutter individually (phase per vertex group), branches sway together.
        disp = np.stack([np.sin(ph), np.cos(1.3 * ph), 0.4 * np.sin(0.7 * ph)], 1)
        return sc.vertices + (w.amplitude_m * sc.vertex_sway)[:, None] * disp

    def render(self, T_world_cam: np.ndarray, t: float = 0.0) -> RenderOutput:
        """Noise-free render from camera pose T_world_cam (optical frame) at time t."""
        K = self.K
        moving = self.vertices_at(t)
        if moving is not None:
            rc = self._raycaster(moving)
        else:
            if self._static is None:
                self._static = self._raycaster(self.scene.vertices)
            rc = self._static
        R = T_world_cam[:3, :3]
        dirs = self._dirs_cam @ R.T.astype(np.float32)
        rays = np.hstack([np.broadcast_to(T_world_cam[:3, 3].astype(np.float32), dirs.shape), dirs])
        hit = rc.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
        t_hit = hit["t_hit"].numpy()
        ok = np.isfinite(t_hit)
        sc = self.scene
        # Misses index a sentinel "sky" triangle so that every array below is full-size (no masked copies).
        sky_id = len(sc.triangles)
        prim = np.where(ok, hit["primitive_ids"].numpy(), sky_id).astype(np.int64)
        t_hit = np.where(ok, t_hit, 0.0).astype(np.float32)
        cls = self._cls_ext[prim]
        inst = self._inst_ext[prim]
        if moving is not None:
            # Rest-position hit point from barycentric coordinates (texture sticks to moving leaves).
            uv = hit["primitive_uvs"].numpy()
            tv = self._vertices32[self._tri_ext[prim]]  # (HW, 3, 3)
            bu, bv = uv[:, 0:1], uv[:, 1:2]
            p_rest = (1 - bu - bv) * tv[:, 0] + bu * tv[:, 1] + bv * tv[:, 2]
        else:
            p_rest = rays[:, :3] + t_hit[:, None] * dirs
        n = hit["primitive_normals"].numpy()
        n = n * np.where(np.einsum("ij,ij->i", n, dirs) > 0, -1.0, 1.0).astype(np.float32)[:, None]
        color = self._shade(p_rest, n, cls, self._albedo_ext[prim])
        color = np.where(ok[:, None], color, self._sky(dirs))
        p_rest[~ok] = 0.0
        H, W = K.height, K.width
        return RenderOutput(
            depth=t_hit.reshape(H, W),
            color=np.clip(color * 255.0, 0, 255).astype(np.uint8).reshape(H, W, 3),
            cls=cls.reshape(H, W), inst=inst.reshape(H, W), tri=np.where(ok, prim, -1).reshape(H, W),
            points=p_rest.reshape(H, W, 3),
        )

    def _sky(self, d: np.ndarray) -> np.ndarray:
        elev = d[:, 2] / np.linalg.norm(d, axis=1)
        base = np.array([0.62, 0.74, 0.9], np.float32)
        top = np.array([0.42, 0.58, 0.86], np.float32)
        a = np.clip(elev, 0, 1)[:, None]
        return base * (1 - a) + top * a

    # Texture scale per class (lattice cells per metre, x y z): bark furrows run along the axis.
    _TEX_SCALE = {
        Cls.GROUND: (25.0, 25.0, 25.0), Cls.TRUNK: (60.0, 60.0, 9.0), Cls.BRANCH: (60.0, 60.0, 9.0),
        Cls.POST: (50.0, 50.0, 6.0), Cls.LEAF: (40.0, 40.0, 40.0), Cls.HEDGE: (30.0, 30.0, 30.0),
        Cls.WEED: (40.0, 40.0, 40.0), Cls.FRUIT: (70.0, 70.0, 70.0), Cls.WIRE: (10.0, 10.0, 10.0),
    }
    _TEX_GAIN = {Cls.GROUND: (0.5, 1.0), Cls.TRUNK: (0.45, 1.1), Cls.BRANCH: (0.45, 1.1), Cls.POST: (0.5, 1.0),
                 Cls.LEAF: (0.65, 0.7), Cls.HEDGE: (0.5, 1.0), Cls.WEED: (0.65, 0.7), Cls.FRUIT: (0.8, 0.4),
                 Cls.WIRE: (0.9, 0.2)}

    def _shade(self, p: np.ndarray, n: np.ndarray, cls: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        lut_scale = np.ones((len(Cls), 3), np.float32)
        lut_gain = np.ones((len(Cls), 2), np.float32)
        for c, sc in self._TEX_SCALE.items():
            lut_scale[c] = sc
            lut_gain[c] = self._TEX_GAIN[c]
        g = lut_gain[cls]
        tex = g[:, 0] + g[:, 1] * self.noise.fbm(p * lut_scale[cls], 2)
        alb = albedo
        ground = cls == Cls.GROUND
        if ground.any():
            # Soil and turf patches at the metre scale.
            mix = np.clip((self.noise(p[ground] * np.float32(1.5)) - 0.45) * 4, 0, 1)[:, None]
            alb = albedo.copy()
            alb[ground] = (np.array([0.44, 0.35, 0.25], np.float32) * (1 - mix)
                           + np.array([0.30, 0.44, 0.17], np.float32) * mix)
        ndl = n @ _SUN.astype(np.float32)
        foliage = (cls == Cls.LEAF) | (cls == Cls.HEDGE) | (cls == Cls.WEED)
        # Foliage transmits light: back-lit leaves are not black.
        diffuse = np.where(foliage, np.abs(ndl) * 0.8, np.clip(ndl, 0, 1))
        light = 0.45 + 0.75 * diffuse
        return alb * (tex * light)[:, None]


@dataclass(frozen=True)
class SensorModel:
    """RealSense-like depth and colour degradation (all rates per pixel)."""

    depth_sigma_coeff: float  # sd = coeff * z^2 (m)
    depth_min_m: float
    depth_max_m: float
    dropout: float
    edge_missing: float
    flying_pixels: float
    color_noise_sd: float
    exposure_jitter: float

    def apply(self, out: RenderOutput, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Noisy (color uint8 (H, W, 3), depth float32 metres (H, W), 0 = missing)."""
        z = out.depth
        valid = z > 0
        # Depth edges: neighbours differing by more than a few centimetres.
        zp = np.pad(np.where(valid, z, 100.0), 1, mode="edge")
        neigh = np.stack([zp[:-2, 1:-1], zp[2:, 1:-1], zp[1:-1, :-2], zp[1:-1, 2:]])
        jump = np.abs(neigh - z[None])
        thresh = 0.03 + 0.03 * z
        edge = valid & np.any(jump > thresh[None], axis=0)
        far = np.max(np.where(jump > thresh[None], neigh, 0.0), axis=0)
        noisy = z + rng.standard_normal(z.shape, dtype=np.float32) * np.float32(self.depth_sigma_coeff) * z * z
        u = rng.random(z.shape, dtype=np.float32)
        fly = edge & (u < self.flying_pixels)
        far = np.where(far > 50.0, z + 1.5, far)  # edge against the sky: fly towards the far range
        mix = rng.random(z.shape, dtype=np.float32)
        noisy = np.where(fly, z + mix * (far - z), noisy)
        missing = (~valid) | (edge & (u >= self.flying_pixels) & (u < self.flying_pixels + self.edge_missing))
        missing |= rng.random(z.shape, dtype=np.float32) < self.dropout
        noisy = np.where(missing | (noisy < self.depth_min_m) | (noisy > self.depth_max_m), 0.0, noisy)

        gain = 1.0 + rng.normal(0.0, self.exposure_jitter)
        col = out.color.astype(np.float32) * np.float32(gain) + rng.standard_normal(out.color.shape, dtype=np.float32) * np.float32(self.color_noise_sd)
        return np.clip(col, 0, 255).astype(np.uint8), noisy.astype(np.float32)
