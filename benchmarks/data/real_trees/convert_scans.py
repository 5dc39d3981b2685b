"""Convert public TLS tree scans (LAZ) once into the small quantised .npz files beside this script.

Run once (needs `laspy` and `lazrs`, not part of the runtime requirements):

    git --git-dir=<mirror of tiagodc/TreeLS> show HEAD:inst/extdata/pine.laz > /tmp/scans/pine.laz
    git --git-dir=<mirror of truebelief/artemis_treeiso> show HEAD:data/LPine1_demo.laz > /tmp/scans/lpine.laz
    .venv/bin/python benchmarks/data/real_trees/convert_scans.py /tmp/scans

Per tree it writes, in the scan's own metres (not yet scaled to orchard size; the row generator scales):
  points   (N, 3) int16, millimetres, x/y relative to the trunk at the scan's ground, z above the scan's ground
  axis     (K, 3) float32 m, rough trunk centre line (slice centres, same frame): a start for the truth's own fit
  source   str
The trunk region (within 0.6 m of the axis) keeps every point; the rest is thinned on a voxel grid.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
TREELS_DIR = HERE / "treels_gpl3"
ARTEMIS_DIR = HERE / "artemis_treeiso_mit"


def _read(path: Path) -> np.ndarray:
    import laspy  # conversion-time dependency only

    las = laspy.read(str(path))
    return np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], 1).astype(np.float64)


def _voxel_thin(p: np.ndarray, voxel: float, rng: np.random.Generator) -> np.ndarray:
    key = np.floor(p / voxel).astype(np.int64)
    order = rng.permutation(len(p))
    _, first = np.unique(key[order], axis=0, return_index=True)
    return p[order[first]]


def _densest(xy: np.ndarray, cell: float = 0.03) -> np.ndarray:
    """The centre of the densest 3x3-cell block of a 2D point set (a trunk's cross-section is the densest spot)."""
    lo = xy.min(0)
    q = np.floor((xy - lo) / cell).astype(int)
    H = np.zeros(q.max(0) + 3)
    np.add.at(H, (q[:, 0] + 1, q[:, 1] + 1), 1)
    S = sum(np.roll(np.roll(H, a, 0), b, 1) for a in (-1, 0, 1) for b in (-1, 0, 1))
    i, j = np.unravel_index(np.argmax(S), S.shape)
    return lo + (np.array([i, j]) - 0.5) * cell


def _circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    A = np.column_stack([2 * xy, np.ones(len(xy))])
    b = np.sum(xy**2, 1)
    (cx, cy, c), *_ = np.linalg.lstsq(A, b, rcond=None)
    return np.array([cx, cy]), float(np.sqrt(max(c + cx * cx + cy * cy, 0.0)))


def trunk_axis(p: np.ndarray, z_ground: float, heights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Slice centres (K, 3) and radii (K,) of the trunk, tracked upwards from the densest spot low down."""
    centres, radii = [], []
    guess = None
    for h in heights:
        s = p[np.abs(p[:, 2] - z_ground - h) < 0.05]
        if guess is not None:
            s = s[np.linalg.norm(s[:, :2] - guess, axis=1) < 0.5]
        if len(s) < 30:
            continue
        c0 = _densest(s[:, :2]) if guess is None else guess
        sel = s[np.linalg.norm(s[:, :2] - c0, axis=1) < 0.35, :2]
        if len(sel) < 20:
            continue
        c, r = _circle(sel)
        for _ in range(4):
            d = np.linalg.norm(sel - c, axis=1)
            sel_in = sel[np.abs(d - r) < max(0.3 * r, 0.02)]
            if len(sel_in) < 15:
                break
            c, r = _circle(sel_in)
            sel = s[np.linalg.norm(s[:, :2] - c, axis=1) < r + max(0.5 * r, 0.04), :2]
        if not 0.02 < r < 0.4:
            continue
        centres.append([c[0], c[1], z_ground + h])
        radii.append(r)
        guess = c
    return np.array(centres), np.array(radii)


def convert_tree(p: np.ndarray, source: str, rng: np.random.Generator, heights: np.ndarray) -> dict:
    z_ground = float(np.percentile(p[:, 2], 0.3))
    centres, radii = trunk_axis(p, z_ground, heights)
    if len(centres) < 5:
        raise RuntimeError(f"{source}: trunk not found")
    base_xy = centres[0, :2]
    q = p - np.array([base_xy[0], base_xy[1], z_ground])
    q = q[q[:, 2] > -0.05]
    ax = centres - np.array([base_xy[0], base_xy[1], z_ground])
    # Distance of every point from the piecewise axis (interpolated by height).
    ax_xy = np.stack([np.interp(q[:, 2], ax[:, 2], ax[:, k]) for k in (0, 1)], 1)
    near = np.linalg.norm(q[:, :2] - ax_xy, axis=1) < 0.6
    keep = np.vstack([q[near], _voxel_thin(q[~near], 0.03, rng)])
    if len(keep) > 70000:
        keep = keep[rng.choice(len(keep), 70000, replace=False)]
    mm = np.round(keep * 1000.0)
    if np.abs(mm).max() > 32767:
        raise RuntimeError(f"{source}: extent beyond int16 millimetres")
    print(f"{source}: {len(p)} -> {len(keep)} points, height {keep[:, 2].max():.1f} m, "
          f"trunk radius {np.median(radii[:5]):.3f} m at {ax[:5, 2].round(1).tolist()} m")
    return {"points": mm.astype(np.int16), "axis": ax.astype(np.float32), "source": np.array(source)}


def main(scan_dir: str) -> None:
    d = Path(scan_dir)
    rng = np.random.default_rng(0)
    TREELS_DIR.mkdir(exist_ok=True)
    ARTEMIS_DIR.mkdir(exist_ok=True)
    hs = np.arange(0.6, 8.01, 0.4)
    for name in ("pine",):  # spruce.laz: branches to the ground hide the trunk in every slice (README)
        t = convert_tree(_read(d / f"{name}.laz"), f"tiagodc/TreeLS inst/extdata/{name}.laz", rng, hs)
        np.savez_compressed(TREELS_DIR / f"{name}.npz", **t)
    plot = _read(d / "lpine.laz")
    # Trees cut out of the plot by their trunk positions in a slice 1.1-1.5 m above the ground (see README).
    for k, xy in enumerate(((2.70, -0.56), (-0.06, 3.03), (8.79, 3.81), (13.11, 0.10))):  # (7.16, 2.23): too thin
        cyl = plot[np.linalg.norm(plot[:, :2] - np.array(xy), axis=1) < 1.3]
        t = convert_tree(cyl, f"truebelief/artemis_treeiso data/LPine1_demo.laz tree at ({xy[0]}, {xy[1]}) m",
                         rng, hs)
        np.savez_compressed(ARTEMIS_DIR / f"lpine_{k}.npz", **t)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "/tmp/scans")
