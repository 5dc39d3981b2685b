"""RGB-D rendering of a Scene with Open3D's RaycastingScene, plus a RealSense-like sensor model.

One ray per pixel through the colour camera's pinhole (no distortion); depth is
aligned to colour by construction. Colour comes from per-triangle albedo,
procedural 3D textures evaluated at the surface's rest position (so texture
stays on leaves that move in wind) and Lambertian shading under a fixed sun.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.sim.scenario import CameraSpec
from orchard_mapping.sim.scene import Cls, Scene


class SurfaceTexture:
    """Periodic multi-scale noise image, mapped onto surfaces by planar projection.

    Each hit point is projected along the dominant axis of its surface normal
    (the cheap half of triplanar mapping) and looked up with bilinear
    interpolation (cv2.remap, wrapping). Texture is fixed to the surface, so
    features are trackable; 2048 px at the finest scale below repeat only
    every ~6 m, and the soil/turf layer uses an incommensurate scale.
    """

    def __init__(self, seed: int, size: int = 2048) -> None:
        rng = np.random.default_rng(seed)
        spec = np.fft.rfft2(rng.standard_normal((size, size)).astype(np.float32))
        fy = np.fft.fftfreq(size)[:, None]
        fx = np.fft.rfftfreq(size)[None, :]
        f2 = fx ** 2 + fy ** 2
        img = np.zeros((size, size), np.float64)
        for sigma, weight in ((1.2, 0.35), (3.5, 0.35), (10.0, 0.3)):  # px: fine grain, blobs, patches
            layer = np.fft.irfft2(spec * np.exp(-2 * (np.pi * sigma) ** 2 * f2), s=(size, size))
            img += weight * layer / layer.std()
        img = (img - img.mean()) / (4 * img.std()) + 0.5
        self.image = np.clip(img, 0, 1).astype(np.float32)

    def lookup(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Texture at texel coordinates u, v (same shape, float32)."""
        # cv2.remap takes maps under 32767 rows and columns: lay any count out as rows of 1024 (padded).
        shape, n = u.shape, u.size
        rows = -(-n // 1024)
        uv = np.zeros((2, rows * 1024), np.float32)
        uv[0, :n] = u.ravel()
        uv[1, :n] = v.ravel()
        out = cv2.remap(self.image, uv[0].reshape(rows, 1024), uv[1].reshape(rows, 1024), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_WRAP)
        return out.ravel()[:n].reshape(shape)


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
        self.texture = SurfaceTexture(seed + 101)
        self._static: o3d.t.geometry.RaycastingScene | None = None
        self._vertices32 = scene.vertices.astype(np.float32)
        self._tri_ext = np.vstack([scene.triangles, [[0, 0, 0]]])
        self._cls_ext = np.append(scene.tri_cls, np.uint8(Cls.SKY))
        self._inst_ext = np.append(scene.tri_inst, np.int32(-1))
        self._albedo_ext = np.vstack([scene.tri_albedo, np.zeros((1, 3), np.float32)])
        self._lut = self._luts()  # per-class texture tables: the scene's appearance is fixed
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
        n_px = len(self._dirs_cam)
        rays = np.empty((n_px, 6), np.float32)  # (HW, 6): origin, direction, as cast_rays takes them
        rays[:, :3] = T_world_cam[:3, 3]
        dirs = rays[:, 3:]
        np.matmul(self._dirs_cam, T_world_cam[:3, :3].T.astype(np.float32), out=dirs)
        hit = rc.cast_rays(o3d.core.Tensor.from_numpy(rays))
        t_hit = hit["t_hit"].numpy()
        ok = np.isfinite(t_hit)
        sc = self.scene
        # Misses index a sentinel "sky" triangle so that every array below is full-size (no masked copies).
        sky_id = len(sc.triangles)
        prim = np.where(ok, hit["primitive_ids"].numpy(), sky_id).astype(np.int64)
        t_hit = np.where(ok, t_hit, np.float32(0.0))
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
        n = hit["primitive_normals"].numpy()  # (HW, 3), turned below to face the camera
        away = np.einsum("ij,ij->i", n, dirs) > 0
        n[away] = -n[away]
        color = self._shade(p_rest, n, cls, self._albedo_ext[prim])
        miss = ~ok
        color[miss] = self._sky(dirs[miss])
        blur = self.scene.scenario.appearance.blur_sigma_px
        if blur > 0:  # optical blur (domain randomisation of training frames)
            color = cv2.GaussianBlur(color.reshape(K.height, K.width, 3), (0, 0), blur).reshape(-1, 3)
        p_rest[miss] = 0.0
        color *= np.float32(255.0)
        np.clip(color, 0, 255, out=color)
        H, W = K.height, K.width
        return RenderOutput(
            depth=t_hit.reshape(H, W),
            color=color.astype(np.uint8).reshape(H, W, 3),
            cls=cls.reshape(H, W), inst=inst.reshape(H, W), tri=np.where(ok, prim, -1).reshape(H, W),
            points=p_rest.reshape(H, W, 3),
        )

    def _sky(self, d: np.ndarray) -> np.ndarray:
        elev = d[:, 2] * (1.0 / np.sqrt(np.einsum("ij,ij->i", d, d)))
        ap = self.scene.scenario.appearance
        base = np.array(ap.sky_horizon_rgb, np.float32)
        top = np.array(ap.sky_zenith_rgb, np.float32)
        a = np.clip(elev, 0, 1)[:, None]
        return base * (1 - a) + top * a

    # Texels per metre per class along (the two in-plane axes, the vertical axis): bark furrows
    # run along the (near-vertical) trunk axis, so vertical texels are stretched.
    _TEX_SCALE = {
        Cls.GROUND: (330.0, 330.0), Cls.TRUNK: (700.0, 120.0), Cls.BRANCH: (700.0, 120.0),
        Cls.POST: (600.0, 80.0), Cls.LEAF: (500.0, 500.0), Cls.HEDGE: (250.0, 250.0),
        Cls.WEED: (500.0, 500.0), Cls.FRUIT: (900.0, 900.0), Cls.WIRE: (100.0, 100.0),
    }
    _FOLIAGE = np.isin(np.arange(len(Cls)), [Cls.LEAF, Cls.HEDGE, Cls.WEED])  # (len(Cls),) bool
    _TEX_GAIN = {Cls.GROUND: (0.45, 1.1), Cls.TRUNK: (0.4, 1.2), Cls.BRANCH: (0.4, 1.2), Cls.POST: (0.45, 1.1),
                 Cls.LEAF: (0.6, 0.8), Cls.HEDGE: (0.45, 1.1), Cls.WEED: (0.6, 0.8), Cls.FRUIT: (0.75, 0.5),
                 Cls.WIRE: (0.9, 0.2)}

    def _luts(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-class lookup tables (len(Cls),): texels per metre (in-plane, vertical), texture offset and gain."""
        ap = self.scene.scenario.appearance
        scale = np.full((len(Cls), 2), 300.0, np.float32)
        gain = np.ones((len(Cls), 2), np.float32)
        for c, sc in self._TEX_SCALE.items():
            scale[c] = sc
            gain[c] = self._TEX_GAIN[c]
        gain[Cls.TRUNK] = gain[Cls.BRANCH] = ap.bark_texture_gain
        if ap.texture_scale != 1.0:
            scale *= np.float32(ap.texture_scale)
        return (np.ascontiguousarray(scale[:, 0]), np.ascontiguousarray(scale[:, 1]),
                np.ascontiguousarray(gain[:, 0]), np.ascontiguousarray(gain[:, 1]))

    def _shade(self, p: np.ndarray, n: np.ndarray, cls: np.ndarray, albedo: np.ndarray) -> np.ndarray:
        """Colour (N, 3) float32 in [0, 1] of hit points p (N, 3) with normals n facing the camera; albedo (N, 3)
        is a per-call copy, shaded in place. Lookups by class are one-dimensional tables (cheap gathers)."""
        s_flat, s_vert, g_off, g_amp = self._lut
        s0 = s_flat[cls]
        # Planar projection along the dominant normal axis: z-facing surfaces use (x, y), others (in-plane, z).
        an = np.abs(n)
        z_dom = an[:, 2] >= np.maximum(an[:, 0], an[:, 1])
        use_y = (an[:, 0] > an[:, 1]) & ~z_dom  # x-facing walls: in-plane axis y
        u = np.where(use_y, p[:, 1], p[:, 0]) * s0
        v = np.where(z_dom, p[:, 1] * s0, p[:, 2] * s_vert[cls])
        tex = g_off[cls] + g_amp[cls] * self.texture.lookup(u, v)
        ap = self.scene.scenario.appearance
        alb = albedo
        ground = np.flatnonzero(cls == Cls.GROUND)
        if ground.size:
            # Soil and turf patches at the metre scale (an incommensurate scale of the same image).
            k = np.float32(37.0)
            pg = p[ground]
            mix = np.clip((self.texture.lookup(pg[:, 0] * k + 511.0, pg[:, 1] * k + 97.0) - 0.5) * 5 + 0.5, 0, 1)
            mix = mix[:, None]
            alb[ground] = np.array(ap.soil_rgb, np.float32) * (1 - mix) + np.array(ap.turf_rgb, np.float32) * mix
        sun = np.asarray(ap.sun_dir, float)
        sun = sun / np.linalg.norm(sun)
        ndl = n @ sun.astype(np.float32)
        # Foliage transmits light: back-lit leaves are not black.
        diffuse = np.where(self._FOLIAGE[cls], np.abs(ndl) * np.float32(0.8), np.clip(ndl, 0, 1))
        light = np.float32(ap.ambient) + np.float32(ap.diffuse) * diffuse
        alb *= (tex * light)[:, None]
        return alb


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
    depth_noise_correlation_px: float  # sd (px) of the Gaussian the depth noise is correlated over; 0: white

    @classmethod
    def from_camera(cls, c: CameraSpec) -> "SensorModel":
        """The sensor model a scenario's camera section describes."""
        return cls(c.depth_sigma_coeff, c.depth_min_m, c.depth_max_m, c.dropout, c.edge_missing, c.flying_pixels,
                   c.color_noise_sd, c.exposure_jitter, c.depth_noise_correlation_px)

    def depth_noise(self, shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
        """(H, W) float32 unit-sd noise field: white, or white noise blurred by a Gaussian of
        depth_noise_correlation_px and scaled back to unit sd (filtered white noise has variance
        1 / (4 pi s^2) for a kernel of sd s px)."""
        white = rng.standard_normal(shape, dtype=np.float32)
        s = self.depth_noise_correlation_px
        if s <= 0:
            return white
        return cv2.GaussianBlur(white, (0, 0), s, borderType=cv2.BORDER_REFLECT) * np.float32(np.sqrt(4 * np.pi) * s)

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
        noisy = z + self.depth_noise(z.shape, rng) * np.float32(self.depth_sigma_coeff) * z * z
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
