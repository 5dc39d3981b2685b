"""Raw-depth cleaning of depth fusion (paper: first paragraph of "Trunk Modeling and Local Ground
Estimation"): raw depth that differs largely from the fused depth ray cast into the keyframe is dropped
(`clean_depth`), and floating pixels without 3D neighbours within a distance threshold are removed
(`remove_floating_pixels`, Sotoodeh 2006); with the checks of fusion's inputs (`FusionError`).

Units: depth float32 metres along the optical axis (z), 0 = missing; colour RGB uint8; pixels in px.
"""

from __future__ import annotations

import cv2
import numpy as np

from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.errors import OrchardMappingError


class FusionError(OrchardMappingError):
    """Fusion input is unusable: wrong image shape or dtype, non-finite pose, ... (the message says which)."""


def check_pose(T: np.ndarray, what: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise FusionError(f"{what}: pose must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise FusionError(f"{what}: pose has non-finite entries")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1.0) > 1e-3:
        raise FusionError(f"{what}: pose rotation is not orthonormal")
    return T


def check_depth(depth: np.ndarray, intr: CameraIntrinsics, what: str) -> np.ndarray:
    depth = np.asarray(depth)
    if depth.shape != (intr.height, intr.width):
        raise FusionError(f"{what}: depth shape {depth.shape} != intrinsics (H, W) = ({intr.height}, {intr.width})")
    if not np.issubdtype(depth.dtype, np.floating):
        raise FusionError(f"{what}: depth must be float metres, got dtype {depth.dtype}")
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    # NaN / inf / negative depth means "missing", like 0.
    return np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0))


def check_color(color: np.ndarray, intr: CameraIntrinsics, what: str) -> np.ndarray:
    color = np.asarray(color)
    if color.shape != (intr.height, intr.width, 3):
        raise FusionError(f"{what}: colour shape {color.shape} != ({intr.height}, {intr.width}, 3)")
    if color.dtype != np.uint8:
        raise FusionError(f"{what}: colour must be uint8 RGB, got dtype {color.dtype}")
    return color



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
    depth = check_depth(depth, intr, "remove_floating_pixels")
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
