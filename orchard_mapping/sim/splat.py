"""A second renderer and sensor, independent of `sim/render.py`: point splatting with a z-buffer.

Used by `sim/scan_rows.py` to render rows of real laser-scanned trees (benchmarks/unseen_rows.py), a
domain the product is never trained or tuned on. It differs from `render.py` in method at every step:

* geometry: points (no meshes, no ray casting). Every scene point is projected; the nearest point per pixel
  wins a z-buffer (`np.minimum.at` over pixel indices); each winning point then covers a disc of radius
  `fx * r / z` pixels (r: its own splat radius in metres, from the point spacing), again nearest depth first,
  done as image shifts over the disc's offsets (radius-aware dilation of the z-buffer). Trunk and post
  points splat smaller where their surface is seen obliquely (discs tangent to the surface), so their
  silhouettes are not widened.
* colour: per-point albedo and a view-independent sky/sun shading model, precomputed once.
* sensor (`StereoSensor`): stereo-like depth (noise on disparity with sub-pixel quantisation, so the depth sd
  grows with z^2 by a coefficient of its own; holes in low texture, in the stereo occlusion shadow beside
  near objects and along silhouettes; flying pixels averaged over a matching window), and a camera of its
  own (auto-exposure following the frame's mean, filmic tone curve and gamma, white-balance shift,
  vignetting, shot and read noise, optional motion blur along the image motion).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import cv2
import numpy as np

from orchard_mapping.core.types import CameraIntrinsics

__all__ = ["PCls", "PointScene", "SplatFrame", "SplatRenderer", "StereoSensor"]


class PCls(IntEnum):
    """Point classes of a splatted scene (their own codes, not sim.scene.Cls)."""

    NONE = 0  # sky / no point
    GROUND = 1
    TRUNK = 2
    FOLIAGE = 3
    POST = 4
    WIRE = 5
    FRUIT = 6  # inst: the fruit's index in the row's fruit list


@dataclass
class PointScene:
    """A scene as points (world frame, z up)."""

    xyz: np.ndarray  # (N, 3) float32 m
    radius: np.ndarray  # (N,) float32 m, splat radius (about the local point spacing)
    albedo: np.ndarray  # (N, 3) float32 linear reflectance in [0, 1]
    normal: np.ndarray  # (N, 3) float32 unit (sign free for foliage)
    cls: np.ndarray  # (N,) uint8 PCls
    inst: np.ndarray  # (N,) int32 tree id (trunk, foliage), post index, fruit index, else -1

    def __post_init__(self) -> None:
        n = len(self.xyz)
        for name in ("radius", "albedo", "normal", "cls", "inst"):
            if len(getattr(self, name)) != n:
                raise ValueError(f"PointScene.{name} has {len(getattr(self, name))} rows, xyz has {n}")


@dataclass(frozen=True)
class SplatFrame:
    depth: np.ndarray  # (H, W) float32 m along the optical axis, 0 = no point
    radiance: np.ndarray  # (H, W, 3) float32 linear, noise-free
    cls: np.ndarray  # (H, W) uint8 PCls
    inst: np.ndarray  # (H, W) int32, -1 = none
    index: np.ndarray  # (H, W) int64 scene point index, -1 = none
    points: np.ndarray  # (H, W, 3) float32 world position of the covering point, 0 where none


SUN = np.array([-0.4, 0.35, 0.85])  # towards the sun (world): other than render.py's


def _shade(scene: PointScene) -> np.ndarray:
    """(N, 3) float32 linear radiance: sky light by the normal's elevation plus the sun (no shadows)."""
    s = SUN / np.linalg.norm(SUN)
    n = scene.normal.astype(np.float32)
    ndl = n @ s.astype(np.float32)
    foliage = scene.cls == PCls.FOLIAGE
    sky = np.float32(0.32) + np.float32(0.18) * np.abs(n[:, 2])
    sun = np.where(foliage, np.float32(0.55) * np.abs(ndl), np.float32(0.95) * np.clip(ndl, 0, None))
    # The side of a trunk turned away from the sun still gets light bounced off the ground.
    bounce = np.where(scene.cls == PCls.TRUNK, np.float32(0.12), np.float32(0.0))
    return (scene.albedo * (sky + sun + bounce)[:, None]).astype(np.float32)


class SplatRenderer:
    def __init__(self, scene: PointScene, intrinsics: CameraIntrinsics, max_radius_px: int = 4,
                 near_m: float = 0.12, far_m: float = 14.0) -> None:
        self.scene = scene
        self.K = intrinsics
        self.max_radius_px = int(max_radius_px)
        self.near, self.far = near_m, far_m
        self._xyz = scene.xyz.astype(np.float32)
        self._xyzT = np.ascontiguousarray(self._xyz.T)
        self._normalT = np.ascontiguousarray(scene.normal.T, dtype=np.float32)
        self._oriented = np.isin(scene.cls, [PCls.TRUNK, PCls.POST])
        self._radiance = _shade(scene)
        R = self.max_radius_px
        offs = [(dy, dx, float(np.hypot(dy, dx))) for dy in range(-R, R + 1) for dx in range(-R, R + 1)]
        self._offsets = sorted((o for o in offs if 0 < o[2] <= R + 0.5), key=lambda o: o[2])

    def render(self, T_world_cam: np.ndarray) -> SplatFrame:
        K = self.K
        H, W = K.height, K.width
        R = self.max_radius_px
        Rt = np.ascontiguousarray(T_world_cam[:3, :3].T, dtype=np.float32)
        c = (Rt @ T_world_cam[:3, 3]).astype(np.float32)
        pc = Rt @ self._xyzT  # (3, N) camera frame: R^T x - R^T t (one sgemm; (N, 3) @ (3, 3) is slow)
        z = pc[2] - c[2]
        sel = np.flatnonzero((z > self.near) & (z < self.far))
        z = z[sel]
        x = pc[0, sel] - c[0]
        y = pc[1, sel] - c[1]
        iz = np.float32(1.0) / z
        u = np.rint(np.float32(K.fx) * x * iz + np.float32(K.cx)).astype(np.int64)
        v = np.rint(np.float32(K.fy) * y * iz + np.float32(K.cy)).astype(np.int64)
        inside = (u >= -R) & (u < W + R) & (v >= -R) & (v < H + R)
        sel, u, v, z, x, y = sel[inside], u[inside], v[inside], z[inside], x[inside], y[inside]
        r_m = self.scene.radius[sel]
        o = self._oriented[sel]
        if o.any():
            # Solid surfaces (trunks, posts) splat as discs tangent to the surface, seen edge-on at their
            # silhouettes: the footprint shrinks with |cos| of the view angle (approximated as a smaller
            # round disc) instead of widening the silhouette by a whole radius.
            so = sel[o]
            p = np.stack([x[o], y[o], z[o]])
            nc = Rt @ self._normalT[:, so]
            cos = np.abs(np.einsum("ij,ij->j", nc, p)) / np.linalg.norm(p, axis=0)
            r_m = r_m.copy()
            r_m[o] *= np.float32(0.3) + np.float32(0.7) * cos
        rpx = np.clip(K.fx * r_m / z, 0.5, R + 0.5).astype(np.float32)
        # z-buffer on a padded image (points just outside the frame still splat into it)
        Hp, Wp = H + 2 * R, W + 2 * R
        pix = (v + R) * Wp + (u + R)
        zbuf = np.full(Hp * Wp, np.inf, np.float32)
        np.minimum.at(zbuf, pix, z)
        win = z <= zbuf[pix]
        ibuf = np.full(Hp * Wp, -1, np.int64)
        ibuf[pix[win]] = sel[win]
        rbuf = np.zeros(Hp * Wp, np.float32)
        rbuf[pix[win]] = rpx[win]
        zbuf, ibuf, rbuf = zbuf.reshape(Hp, Wp), ibuf.reshape(Hp, Wp), rbuf.reshape(Hp, Wp)
        # Radius-aware dilation: every pixel takes the nearest splat among the points whose disc reaches it.
        D = zbuf[R:R + H, R:R + W].copy()
        I = ibuf[R:R + H, R:R + W].copy()
        # A source pixel whose disc cannot reach the offset is pushed to infinite depth for it.
        take = np.empty((H, W), bool)
        reach = np.empty((H, W), bool)
        for dy, dx, d in self._offsets:
            sl = (slice(R + dy, R + dy + H), slice(R + dx, R + dx + W))
            np.greater_equal(rbuf[sl], np.float32(d), out=reach)
            np.less(zbuf[sl], D, out=take)
            take &= reach
            np.copyto(D, zbuf[sl], where=take)
            np.copyto(I, ibuf[sl], where=take)
        hit = I >= 0
        depth = np.where(hit, D, np.float32(0.0)).astype(np.float32)
        idx = np.where(hit, I, 0)
        radiance = self._radiance[idx]
        np.copyto(radiance, self._sky(T_world_cam), where=~hit[..., None])
        cls = np.where(hit, self.scene.cls[idx], np.uint8(PCls.NONE)).astype(np.uint8)
        inst = np.where(hit, self.scene.inst[idx], -1).astype(np.int32)
        points = np.where(hit[..., None], self._xyz[idx], np.float32(0.0))
        return SplatFrame(depth, radiance.astype(np.float32), cls, inst, np.where(hit, I, -1), points)

    def _sky(self, T_world_cam: np.ndarray) -> np.ndarray:
        """Overcast-blue sky by elevation, brighter towards the sun (linear radiance (H, W, 3)), evaluated on
        an 8x coarser grid and resized (it is smooth)."""
        K = self.K
        vv, uu = np.mgrid[0:K.height:8, 0:K.width:8]
        vv, uu = vv.ravel() + 3.5, uu.ravel() + 3.5
        gh, gw = -(-K.height // 8), -(-K.width // 8)
        d = np.stack([(uu - K.cx) / K.fx, (vv - K.cy) / K.fy, np.ones(len(uu))], 1) @ T_world_cam[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        elev = np.clip(d[:, 2], 0.0, 1.0)[:, None]
        s = SUN / np.linalg.norm(SUN)
        glow = np.clip(d @ s, 0.0, 1.0)[:, None] ** 8
        horizon = np.array([0.85, 0.88, 0.9])
        zenith = np.array([0.45, 0.58, 0.85])
        sky = ((horizon * (1 - elev) + zenith * elev + 0.4 * glow) * 1.6).astype(np.float32).reshape(gh, gw, 3)
        return cv2.resize(sky, (K.width, K.height), interpolation=cv2.INTER_LINEAR)


@dataclass
class StereoSensor:
    """Stereo depth camera (active-stereo-like, left imager = colour camera) and its colour pipeline."""

    baseline_m: float = 0.05
    disparity_sd_px: float = 0.07  # matching noise on disparity (correlated over a 3x3 window)
    subpixel: float = 1.0 / 8.0  # disparity quantisation (px)
    depth_min_m: float = 0.28
    depth_max_m: float = 8.0
    low_texture: float = 0.025  # grey-level gradient energy below which matching fails
    edge_hole: float = 0.5  # share of silhouette pixels with no depth
    flying: float = 0.25  # share of silhouette pixels averaged over a 5x5 matching window
    speckle: float = 0.004  # random missing depth
    max_occlusion_px: int = 24
    # colour
    target_mean: float = 0.2  # auto-exposure's goal for the frame's mean (linear, after exposure)
    exposure_rate: float = 0.25  # share of the remaining exposure error corrected per frame
    wb_gain: tuple[float, float, float] = (1.07, 1.0, 0.88)  # warm white balance shift
    vignetting: float = 0.38  # relative fall-off at the image corners
    gamma: float = 2.2
    shot_noise: float = 0.012
    read_noise: float = 0.004
    motion_blur_exposure: float = 0.35  # shutter time as a share of the frame interval (0: no blur)
    _exposure: float | None = field(default=None, repr=False)

    def depth_sd(self, z: float, fx: float) -> float:
        """Depth sd (m) at range z: sd_z = z^2 / (f B) * sd_disparity (quantisation included)."""
        sd = np.hypot(self.disparity_sd_px, self.subpixel / np.sqrt(12.0))
        return float(z * z / (fx * self.baseline_m) * sd)

    def apply(self, frame: SplatFrame, fx: float, rng: np.random.Generator,
              blur_px: tuple[float, float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
        """(colour uint8 (H, W, 3) RGB, depth float32 (H, W) m, 0 = missing). blur_px: the image motion (px)
        of the frame's centre over one frame interval (motion blur along it)."""
        color = self._color(frame.radiance, rng, blur_px)
        return color, self._depth(frame.depth, color, fx, rng)

    def _depth(self, z: np.ndarray, color: np.ndarray, fx: float, rng: np.random.Generator) -> np.ndarray:
        H, W = z.shape
        fb = np.float32(fx * self.baseline_m)
        valid = z > 0
        disp = np.where(valid, fb / np.where(valid, z, 1.0), np.float32(0.0)).astype(np.float32)
        # Stereo occlusion: a pixel is hidden from the right imager when a nearer surface lies to its right
        # within the disparity difference.
        occ = np.zeros((H, W), bool)
        for k in range(1, self.max_occlusion_px + 1):
            occ[:, :-k] |= (disp[:, k:] - disp[:, :-k]) >= k
        # Silhouettes: depth jumps to a 4-neighbour.
        zp = np.pad(np.where(valid, z, 50.0), 1, mode="edge")
        neigh = np.stack([zp[:-2, 1:-1], zp[2:, 1:-1], zp[1:-1, :-2], zp[1:-1, 2:]])
        edge = valid & np.any(np.abs(neigh - z[None]) > (0.02 + 0.04 * z)[None], axis=0)
        # Low texture: gradient energy of the grey image over a 9x9 window.
        g = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
        gx = cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)
        tex = np.sqrt(cv2.boxFilter(gx * gx + gy * gy, -1, (9, 9)))
        lt = max(self.low_texture, 1e-9)
        p_flat = np.clip((self.low_texture - tex) / lt, 0.0, 1.0) ** 2 * 0.95
        # Disparity noise, correlated over the matching window, then sub-pixel quantisation.
        n = cv2.boxFilter(rng.standard_normal((H, W)).astype(np.float32), -1, (3, 3)) * np.float32(3.0)
        d_noisy = np.round((disp + n * np.float32(self.disparity_sd_px)) / self.subpixel) * self.subpixel
        out = np.where(d_noisy > 0.5, fb / np.maximum(d_noisy, 0.5), 0.0).astype(np.float32)
        u = rng.random((H, W), dtype=np.float32)
        fly = edge & (u < self.flying)
        win = cv2.blur(np.where(valid, z, 0.0).astype(np.float32), (5, 5))
        cnt = cv2.blur(valid.astype(np.float32), (5, 5))
        out = np.where(fly & (cnt > 0), win / np.maximum(cnt, 1e-6), out)
        missing = (~valid) | occ | (edge & (u >= self.flying) & (u < self.flying + self.edge_hole))
        missing |= rng.random((H, W), dtype=np.float32) < p_flat
        missing |= rng.random((H, W), dtype=np.float32) < self.speckle
        missing |= (out < self.depth_min_m) | (out > self.depth_max_m)
        return np.where(missing, 0.0, out).astype(np.float32)

    def _color(self, radiance: np.ndarray, rng: np.random.Generator, blur_px: tuple[float, float]) -> np.ndarray:
        H, W, _ = radiance.shape
        img = radiance
        bx, by = (self.motion_blur_exposure * b for b in blur_px)
        length = float(np.hypot(bx, by))
        if length > 0.7:
            k = int(np.ceil(length)) | 1
            ker = np.zeros((k, k), np.float32)
            c = k // 2
            for s in np.linspace(-0.5, 0.5, 2 * k + 1):
                ker[int(round(c + s * by)), int(round(c + s * bx))] += 1.0
            img = cv2.filter2D(img, -1, ker / ker.sum(), borderType=cv2.BORDER_REFLECT)
        yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
        r2 = ((xx - W / 2) / (W / 2)) ** 2 + ((yy - H / 2) / (H / 2)) ** 2
        vig = 1.0 - self.vignetting * r2 / 2.0
        img = img * vig[..., None] * np.asarray(self.wb_gain, np.float32)
        lum = img @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        # centre-weighted metering
        mean = float(np.average(lum[::4, ::4], weights=vig[::4, ::4] ** 2))
        goal = self.target_mean / max(mean, 1e-4)
        self._exposure = goal if self._exposure is None else self._exposure + self.exposure_rate * (
            goal - self._exposure)
        x = img * np.float32(self._exposure)
        y = x * (1.0 + x / 6.0) / (1.0 + x)  # filmic shoulder
        y = np.clip(y, 0.0, 1.0)
        y = y + rng.standard_normal(y.shape).astype(np.float32) * (
            np.float32(self.shot_noise) * np.sqrt(y) + np.float32(self.read_noise))
        y = np.clip(y, 0.0, 1.0) ** np.float32(1.0 / self.gamma)
        return np.clip(np.rint(y * 255.0), 0, 255).astype(np.uint8)
