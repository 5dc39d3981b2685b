"""The scene of a row of real laser-scanned trees (sim/scan_rows.py renders and records it): the scans
loaded (benchmarks/data/real_trees/), scaled and placed along the row on a bumpy ground, their trunk truth
by slicing the full 360-degree scan and fitting an algebraic circle per slice, and the sampled posts, wire,
ground and neighbouring rows, as one `PointScene` for the splat renderer.

Frames: the row's world frame (x along the row, z up); metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from orchard_mapping.errors import OrchardMappingError, ScenarioError
from orchard_mapping.sim.scene import Fruit
from orchard_mapping.sim.splat import PCls, PointScene

DEFAULT_DATA_DIR = Path(__file__).resolve().parents[2] / "benchmarks" / "data" / "real_trees"
# m, a tree's local ground: the terrain within this radius of the trunk, on a grid of this cell
LOCAL_GROUND_RADIUS_M = 0.5
GROUND_CELL_M = 0.02


class ScanDataError(OrchardMappingError):
    """The real-tree scan files (benchmarks/data/real_trees/**/*.npz) are missing or unreadable."""


@dataclass(frozen=True)
class ScanTree:
    name: str
    points: np.ndarray  # (N, 3) float64 m, scan scale, trunk at the scan's ground at the origin
    axis: np.ndarray  # (K, 3) float64 m, rough trunk centre line
    source: str


def load_scan_trees(data_dir: str | Path | None = None) -> list[ScanTree]:
    """Every tree under data_dir (default benchmarks/data/real_trees), sorted by file name."""
    d = Path(data_dir) if data_dir is not None else DEFAULT_DATA_DIR
    files = sorted(d.glob("*/*.npz"))
    if not files:
        raise ScanDataError(f"no real-tree scans (*/*.npz) under {d}: see benchmarks/data/real_trees/README.md")
    trees = []
    for f in files:
        try:
            with np.load(f) as z:
                trees.append(ScanTree(f.stem, z["points"].astype(np.float64) / 1000.0,
                                      z["axis"].astype(np.float64), str(z["source"])))
        except (OSError, KeyError, ValueError) as err:
            raise ScanDataError(f"{f}: not a real-tree scan file: {err}") from err
    return trees


@dataclass(frozen=True)
class ScanRowSpec:
    n_trees: int = 6
    spacing_m: tuple[float, float] = (0.9, 1.3)
    height_m: tuple[float, float] = (2.0, 2.8)  # each tree scaled to stand this tall
    offset_jitter_m: float = 0.03
    slope_deg: float = 2.5
    cross_slope_deg: float = 1.5
    bumps_per_m2: float = 0.6
    bump_height_m: tuple[float, float] = (-0.05, 0.06)
    bump_sigma_m: tuple[float, float] = (0.25, 0.7)
    post_every_n_trees: int = 3
    post_diameter_m: float = 0.085
    post_height_m: float = 2.4
    wire_height_m: float = 1.0
    ground_spacing_m: float = 0.012
    background_row_m: float = 3.6  # neighbouring rows at +-this (0: none)
    motion: str = "standard"  # camera path scenario: "standard" or "handheld_walk" (sim/trajectory.py)
    rate_hz: float = 10.0
    width: int = 640
    height: int = 480
    fx: float = 607.3
    fy: float = 607.3
    cx: float = 321.8
    cy: float = 238.4
    margin_m: float = 1.2
    # Fruit in the crowns' outer shell (none by default: the rows measured before fruit existed stay as they
    # were, their fruit draws come from a stream of their own)
    fruit_per_tree: tuple[int, int] = (0, 0)
    fruit_radius_m: tuple[float, float] = (0.033, 0.045)
    fruit_red_fraction: float = 0.6


class BumpyGround:
    """Ground z = h(x, y): slope, cross slope, Gaussian bumps and hollows (its own form)."""

    def __init__(self, rng: np.random.Generator, spec: ScanRowSpec, x_range: tuple[float, float],
                 y_half: float) -> None:
        self.slope = float(np.tan(np.radians(spec.slope_deg)))
        self.cross = float(np.tan(np.radians(spec.cross_slope_deg)))
        area = (x_range[1] - x_range[0]) * 2 * y_half
        n = max(1, int(rng.poisson(spec.bumps_per_m2 * area)))
        self.c = np.stack([rng.uniform(*x_range, n), rng.uniform(-y_half, y_half, n)], 1)
        self.a = rng.uniform(*spec.bump_height_m, n)
        self.s = rng.uniform(*spec.bump_sigma_m, n)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        z = self.slope * x + self.cross * y
        flat_x, flat_y = x.reshape(-1), y.reshape(-1)
        acc = np.zeros(flat_x.shape)
        for k in range(0, len(self.a), 64):
            dx = flat_x[:, None] - self.c[None, k:k + 64, 0]
            dy = flat_y[:, None] - self.c[None, k:k + 64, 1]
            acc += np.sum(self.a[k:k + 64] * np.exp(-(dx * dx + dy * dy) / (2 * self.s[k:k + 64] ** 2)), axis=1)
        return z + acc.reshape(x.shape)

    def normal(self, x: np.ndarray, y: np.ndarray, eps: float = 0.01) -> np.ndarray:
        gx = (self.height(x + eps, y) - self.height(x - eps, y)) / (2 * eps)
        gy = (self.height(x, y + eps) - self.height(x, y - eps)) / (2 * eps)
        n = np.stack([-gx, -gy, np.ones_like(gx)], -1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


# ----------------------------------------------------------------------------------------------- truth fits
def fit_circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic (Kasa) circle fit of 2D points (N, 2): (centre (2,), radius). Solves
    x^2 + y^2 = 2 a x + 2 b y + c in least squares; r^2 = c + a^2 + b^2."""
    xy = np.asarray(xy, float)
    m = xy.mean(0)  # centred for conditioning
    q = xy - m
    A = np.column_stack([2 * q, np.ones(len(q))])
    (a, b, c), *_ = np.linalg.lstsq(A, np.sum(q * q, 1), rcond=None)
    return m + np.array([a, b]), float(np.sqrt(max(c + a * a + b * b, 0.0)))


def _plane_basis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(a, e1)


@dataclass(frozen=True)
class TrunkSlices:
    heights: np.ndarray  # (S,) m along the axis above the reference point
    centres: np.ndarray  # (S, 3) world
    radii: np.ndarray  # (S,) m
    point: np.ndarray  # (3,) axis line point
    axis: np.ndarray  # (3,) unit, up


def trunk_slices(pts: np.ndarray, origin: np.ndarray, axis: np.ndarray, r0: float,
                 heights: np.ndarray, slab_m: float = 0.02, iters: int = 3) -> TrunkSlices:
    """Slice the points (N, 3) perpendicular to a trunk axis guess (origin, axis) at `heights` (along the axis
    from origin), fit a circle per slice (trimmed: points within max(0.25 r, 3 mm) of the circle), refit the
    axis as the line through the slice centres, repeat. r0: rough radius (selects the slice's points)."""
    a = axis / np.linalg.norm(axis)
    o = np.asarray(origin, float)
    radii_prev = np.full(len(heights), r0)
    for _ in range(iters):
        e1, e2 = _plane_basis(a)
        d = pts - o
        h = d @ a
        q = np.stack([d @ e1, d @ e2], 1)
        hs, cs, rs = [], [], []
        for k, hk in enumerate(heights):
            rk = radii_prev[k]
            s = q[(np.abs(h - hk) < slab_m / 2) & (np.linalg.norm(q, axis=1) < 1.6 * rk + 0.01)]
            if len(s) < 12:
                continue
            c, r = fit_circle(s)
            for _ in range(4):
                inl = s[np.abs(np.linalg.norm(s - c, axis=1) - r) < max(0.25 * r, 0.003)]
                if len(inl) < 10:
                    break
                c, r = fit_circle(inl)
            hs.append(hk)
            cs.append(o + hk * a + c[0] * e1 + c[1] * e2)
            rs.append(r)
        if len(cs) < 3:
            raise ScenarioError("trunk slices: fewer than 3 slices with points")
        C = np.array(cs)
        m = C.mean(0)
        _, _, vt = np.linalg.svd(C - m)
        a_new = vt[0] if vt[0] @ a > 0 else -vt[0]
        o = m + ((o - m) @ a_new) * a_new
        a = a_new
        radii_prev = np.interp(heights, hs, rs)
    return TrunkSlices(np.array(hs), C, np.array(rs), o, a)


def local_ground_plane(ground: BumpyGround, x: float, y: float, cells: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of the terrain over the 2 cm cells of the 0.5 m disk round (x, y) (or the given
    cells (M, 2) of cell centres): its point under (x, y) and unit up normal."""
    if cells is None:
        g = np.arange(-LOCAL_GROUND_RADIUS_M + GROUND_CELL_M / 2, LOCAL_GROUND_RADIUS_M, GROUND_CELL_M)
        gx, gy = np.meshgrid(g, g)
        keep = gx**2 + gy**2 < LOCAL_GROUND_RADIUS_M**2
        px, py = x + gx[keep], y + gy[keep]
    else:
        px, py = cells[:, 0], cells[:, 1]
    pz = ground.height(px, py)
    A = np.stack([px - x, py - y, np.ones_like(px)], 1)
    (gx_, gy_, c), *_ = np.linalg.lstsq(A, pz, rcond=None)
    n = np.array([-gx_, -gy_, 1.0])
    return np.array([x, y, c]), n / np.linalg.norm(n)


# ----------------------------------------------------------------------------------------------- scene
@dataclass
class PlacedTree:
    id: int
    scan: str
    points: np.ndarray  # (N, 3) world
    trunk: np.ndarray  # (N,) bool
    base: np.ndarray  # (3,) axis at the local ground plane
    axis: np.ndarray  # (3,) unit
    ground_point: np.ndarray
    ground_normal: np.ndarray
    slices: TrunkSlices
    clear_height: float
    height: float
    scale: float


def _smooth_noise(p: np.ndarray, rng: np.random.Generator, scales: tuple[float, ...]) -> np.ndarray:
    """(N,) value in ~[-1, 1]: sums of random plane waves at the given wavelengths (m), fixed to the points."""
    out = np.zeros(len(p))
    for lam in scales:
        for _ in range(3):
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            out += np.sin(p @ d * (2 * np.pi / lam) + rng.uniform(0, 2 * np.pi))
    return out / (3 * len(scales)) * 1.7


def _normals(p: np.ndarray, k: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """(unit normals (N, 3) by local PCA, distance (N,) to the 3rd nearest neighbour)."""
    tree = cKDTree(p)
    dist, idx = tree.query(p, k=k)
    nb = p[idx] - p[idx].mean(1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vec = np.linalg.eigh(cov)
    return vec[:, :, 0], dist[:, 3]


def _place_tree(i: int, scan: ScanTree, x: float, y: float, ground: BumpyGround, rng: np.random.Generator,
                spec: ScanRowSpec) -> PlacedTree:
    top = float(scan.points[:, 2].max())
    scale = rng.uniform(*spec.height_m) / top
    yaw = rng.uniform(0, 2 * np.pi)
    Rz = Rotation.from_euler("z", yaw).as_matrix()
    q = scan.points * scale
    ax = scan.axis * scale
    # the scan's own ground litter (low points away from the trunk) stays behind
    ax_xy = np.stack([np.interp(q[:, 2], ax[:, 2], ax[:, k]) for k in (0, 1)], 1)
    r_axis = np.linalg.norm(q[:, :2] - ax_xy, axis=1)
    q = q[(q[:, 2] > -0.01) & ~((q[:, 2] < 0.06) & (r_axis > 0.05))]
    gz = float(ground.height(np.array(x), np.array(y)))
    offset = np.array([x, y, gz - 0.012])  # sunk a little: bumps must not leave the trunk floating
    pts = q @ Rz.T + offset
    ax_w = ax @ Rz.T + offset
    gp, gn = local_ground_plane(ground, x, y)
    a0 = ax_w[-1] - ax_w[0]
    a0 /= np.linalg.norm(a0)
    r0 = 1.3 * float(np.median(scan_radius_guess(scan))) * scale
    sl = trunk_slices(pts, ax_w[0], a0, r0, np.arange(-0.04, 0.8, 0.02))
    # axis at the local ground plane: intersect the fitted line with the plane
    t = ((gp - sl.point) @ gn) / (sl.axis @ gn)
    base = sl.point + t * sl.axis
    sl_h = (sl.centres - base) @ gn  # slice heights above the local ground (along its normal)
    # trunk points: within 1.35 r (+4 mm) of the fitted axis (radius by height, last slice's above)
    d = pts - base
    along = d @ sl.axis
    radial = np.linalg.norm(d - along[:, None] * sl.axis, axis=1)
    r_at = np.interp(along, sl.heights - (base - sl.point) @ sl.axis, sl.radii)
    trunk = radial < 1.35 * r_at + 0.004
    hgt = d @ gn
    crown = pts[(~trunk) & (radial < 0.35) & (hgt > 0.1)]
    clear = float(np.clip(np.percentile((crown - base) @ gn, 2) if len(crown) > 50 else 0.8, 0.45, 1.2))
    # TLS ranging noise and mixed-pixel ghosts stand off the bark (5-11 % of the plot scan's trunk points
    # 3-20 mm outside the fitted circle after scaling): not geometry a camera would see, and splatted they
    # widen the trunk's silhouette by up to a centimetre. Statistical clean-up of the clear trunk: points
    # more than 3 mm outside the slice circle go.
    ghost = trunk & (hgt < clear) & (radial - r_at > 0.003)
    keep = ~ghost
    # The plot scan's ranging noise (sd ~1.5 mm after scaling) makes the outer envelope of the points, what
    # a camera's silhouette shows, stand ~3 mm off the mean surface: radial residuals of the clear trunk
    # are smoothed to 30 % (bark roughness kept, ranging noise mostly gone).
    sm = trunk & (hgt < clear) & (radial > 1e-6)
    shrink = np.where(sm, (r_at + 0.3 * (radial - r_at)) / np.maximum(radial, 1e-6), 1.0)
    ax_pt = base + along[:, None] * sl.axis
    pts = ax_pt + (pts - ax_pt) * shrink[:, None]
    del sl_h
    return PlacedTree(i, scan.name, pts[keep], trunk[keep], base, sl.axis, gp, gn, sl, clear,
                      float(hgt[keep].max()), scale)


def scan_radius_guess(scan: ScanTree) -> np.ndarray:
    """Rough trunk radii (m, scan scale) at the first axis slices (points within 0.35 m of the axis point)."""
    out = []
    for c in scan.axis[:4]:
        s = scan.points[np.abs(scan.points[:, 2] - c[2]) < 0.05]
        s = s[np.linalg.norm(s[:, :2] - c[:2], axis=1) < 0.35, :2]
        if len(s) >= 12:
            out.append(fit_circle(s)[1])
    return np.array(out or [0.12])


@dataclass
class ScanRowScene:
    spec: ScanRowSpec
    ground: BumpyGround
    trees: list[PlacedTree]
    posts: list[dict]
    points: PointScene
    row_x: tuple[float, float]
    fruit: list[Fruit] = field(default_factory=list)


_FRUIT_STREAM = 0xF2017  # the fruit's draws (seed, this): the rows without fruit keep every other draw
FRUIT_POINT_SPACING_M = 0.0025


def _fibonacci_sphere(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    r = np.sqrt(1 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _place_fruit(t: PlacedTree, n: int, spec: ScanRowSpec, rng: np.random.Generator) -> list[Fruit]:
    """Up to n fruit hanging in the outer shell of tree t's crown: centred just outside a crown point that lies
    in the outer 30 % of its 20 cm height band's reach from the crown's centre line, between 15 cm above the
    clear trunk and 85 % of the tree's height, no two fruit interpenetrating."""
    fol = t.points[~t.trunk]
    h = (fol - t.ground_point) @ t.ground_normal
    band = np.floor(h / 0.2).astype(int)
    centre = np.zeros((len(fol), 2))
    reach = np.zeros(len(fol))
    for b in np.unique(band):
        m = band == b
        c = np.median(fol[m, :2], axis=0)
        centre[m] = c
        reach[m] = np.percentile(np.linalg.norm(fol[m, :2] - c, axis=1), 95)
    rad = fol[:, :2] - centre
    r_xy = np.linalg.norm(rad, axis=1)
    ok = (h > t.clear_height + 0.15) & (h < 0.85 * t.height) & (r_xy > 0.7 * reach) & (r_xy > 0.05)
    cand = np.flatnonzero(ok)
    out: list[Fruit] = []
    if not len(cand):
        return out
    for _ in range(n):
        for _try in range(30):
            i = int(cand[rng.integers(len(cand))])
            r = float(rng.uniform(*spec.fruit_radius_m))
            out_dir = np.append(rad[i] / r_xy[i], 0.0)
            c = fol[i] + out_dir * 0.2 * r - np.array([0.0, 0.0, 0.5 * r])  # hanging below its spur
            if all(np.linalg.norm(c - f.position) > r + f.radius + 0.005 for f in out):
                red = bool(rng.uniform() < spec.fruit_red_fraction)
                out.append(Fruit(t.id, c, r, "red" if red else "green"))
                break
    return out


def _fruit_points(fruit: list[Fruit], rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """(xyz, radius, albedo, normal, cls, inst) of the fruit's surface points: this renderer's own fruit look
    (a red fruit: a blush of its own red over a yellow-green ground, mottled by smooth noise and darker
    towards a random side; a green one: green to yellow-green with faint mottling)."""
    parts = []
    for k, f in enumerate(fruit):
        n = max(60, int(4 * np.pi * f.radius**2 / FRUIT_POINT_SPACING_M**2))
        u = _fibonacci_sphere(n)
        p = f.position + f.radius * u
        mottle = _smooth_noise(u * f.radius, rng, (0.012, 0.03))
        if f.color == "red":
            blush = np.array([0.62, 0.07, 0.05]) * (1 - (w := rng.uniform())) + np.array([0.72, 0.24, 0.14]) * w
            ground = np.array([0.64, 0.6, 0.22])
            d = rng.normal(size=3)
            d /= np.linalg.norm(d)
            mix = np.clip(rng.uniform(0.6, 1.0) + 0.5 * (u @ d) + 0.4 * mottle, 0, 1)[:, None]
            alb = ground * (1 - mix) + blush * mix
        else:
            g = rng.uniform()
            alb = np.array([0.4, 0.56, 0.14]) * (1 - g) + np.array([0.62, 0.62, 0.24]) * g
            alb = alb * (1 + 0.12 * mottle)[:, None]
        alb = alb * rng.uniform(0.8, 1.15) * rng.uniform(0.94, 1.06, (n, 1))
        parts.append((p, np.full(n, 0.8 * FRUIT_POINT_SPACING_M), alb, u, np.full(n, PCls.FRUIT, np.uint8),
                      np.full(n, k, np.int32)))
    return tuple(np.concatenate([q[i] for q in parts]) for i in range(6)) if parts else ()


def _cylinder_points(c: np.ndarray, radius: float, height: float, spacing: float, rng: np.random.Generator
                     ) -> tuple[np.ndarray, np.ndarray]:
    n_a = max(8, int(2 * np.pi * radius / spacing))
    n_h = max(2, int(height / spacing))
    th, hh = np.meshgrid(np.arange(n_a) * 2 * np.pi / n_a, np.arange(n_h) * spacing)
    th = th.ravel() + rng.uniform(-0.3, 0.3, th.size) * 2 * np.pi / n_a
    hh = hh.ravel() + rng.uniform(-0.3, 0.3, hh.size) * spacing
    n = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1)
    return c + np.column_stack([radius * n[:, :2], hh]), n


def build_scan_row(seed: int, spec: ScanRowSpec = ScanRowSpec(), trees: list[ScanTree] | None = None
                   ) -> ScanRowScene:
    rng = np.random.default_rng([seed, 0x5CA2])
    pool = trees if trees is not None else load_scan_trees()
    n = spec.n_trees
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(*spec.spacing_m, n - 1))]) if n > 1 else np.zeros(1)
    ys = rng.uniform(-1, 1, n) * spec.offset_jitter_m
    x0, x1 = float(xs[0]), float(xs[-1])
    xr = (x0 - spec.margin_m - 2.0, x1 + spec.margin_m + 2.0)
    y_half = spec.background_row_m + 0.6 if spec.background_row_m > 0 else 3.2
    ground = BumpyGround(rng, spec, xr, y_half)
    picks = rng.permutation(np.resize(rng.permutation(len(pool)), n))
    placed = [_place_tree(i, pool[int(picks[i])], float(xs[i]), float(ys[i]), ground, rng, spec) for i in range(n)]
    fruit: list[Fruit] = []
    if spec.fruit_per_tree[1] > 0:
        f_rng = np.random.default_rng([seed, _FRUIT_STREAM])
        for k, t in enumerate(placed):
            mine = _place_fruit(t, int(f_rng.integers(spec.fruit_per_tree[0], spec.fruit_per_tree[1] + 1)), spec,
                                f_rng)
            if mine:  # the crown's points inside a fruit go (the fruit pushes the needles aside)
                c = np.array([f.position for f in mine])
                r = np.array([f.radius for f in mine])
                d, j = cKDTree(c).query(t.points)
                keep = t.trunk | (d > r[j] + 0.003)
                placed[k] = replace(t, points=t.points[keep], trunk=t.trunk[keep])
            fruit += mine

    parts: list[tuple[np.ndarray, ...]] = []  # (xyz, radius, albedo, normal, cls, inst)
    # --- trees: bark brown-grey with a per-tree tint and furrow noise; needles green, twigs darker
    for t in placed:
        nrm, d3 = _normals(t.points)
        d = t.points - t.base
        radial = d - (d @ t.axis)[:, None] * t.axis
        out = np.einsum("ij,ij->i", nrm, radial) < 0
        nrm[out] = -nrm[out]
        rad = np.clip(0.75 * d3, 0.0008, 0.012)
        tint = rng.uniform(0.8, 1.2) * np.array([1.0, rng.uniform(0.88, 1.0), rng.uniform(0.8, 0.95)])
        bark = np.array([0.29, 0.25, 0.22]) * tint
        furrow = _smooth_noise(d, rng, (0.004, 0.011, 0.03))
        needles_a, needles_b = np.array([0.07, 0.2, 0.06]), np.array([0.2, 0.3, 0.09])
        mixv = np.clip(0.5 + 0.6 * _smooth_noise(t.points, rng, (0.02, 0.07)), 0, 1)[:, None]
        alb = needles_a * (1 - mixv) + needles_b * mixv
        alb *= rng.uniform(0.75, 1.25, (len(alb), 1))  # needle clumps catch light differently
        alb[t.trunk] = bark * (1.0 + 0.45 * furrow[t.trunk])[:, None] * rng.uniform(0.85, 1.15, (t.trunk.sum(), 1))
        cls = np.where(t.trunk, PCls.TRUNK, PCls.FOLIAGE).astype(np.uint8)
        parts.append((t.points, rad, alb, nrm, cls, np.full(len(t.points), t.id, np.int32)))

    # --- posts (straight, untapered) every post_every_n_trees trees and at both ends, and one wire
    posts = []
    post_x = [x0 - 0.55]
    if spec.post_every_n_trees > 0:
        post_x += [0.5 * (xs[k] + xs[k + 1]) for k in range(spec.post_every_n_trees - 1, n - 1,
                                                           spec.post_every_n_trees)]
    post_x.append(x1 + 0.55)
    for k, px in enumerate(post_x):
        gz = float(ground.height(np.array(px), np.array(0.0)))
        c = np.array([px, 0.0, gz - 0.05])
        p, nrm = _cylinder_points(c, spec.post_diameter_m / 2, spec.post_height_m + 0.05, 0.004, rng)
        grain = _smooth_noise(p * np.array([6.0, 6.0, 0.3]), rng, (0.01, 0.03))
        alb = np.array([0.43, 0.41, 0.37]) * (1 + 0.35 * grain)[:, None] * rng.uniform(0.9, 1.1, (len(p), 1))
        parts.append((p, np.full(len(p), 0.0028), alb, nrm, np.full(len(p), PCls.POST, np.uint8),
                      np.full(len(p), k, np.int32)))
        posts.append({"position": [round(px, 5), 0.0, round(gz, 5)], "diameter_m": spec.post_diameter_m,
                      "height_m": spec.post_height_m})
    wx = np.arange(post_x[0], post_x[-1], 0.002)
    wz = np.interp(wx, post_x, [p["position"][2] for p in posts]) + spec.wire_height_m
    wp = np.column_stack([wx, np.zeros_like(wx), wz])
    parts.append((wp, np.full(len(wp), 0.0015), np.tile([0.55, 0.56, 0.58], (len(wp), 1)),
                  np.tile([0.0, -0.6, 0.8], (len(wp), 1)), np.full(len(wp), PCls.WIRE, np.uint8),
                  np.full(len(wp), -1, np.int32)))

    # --- ground: jittered grid; mulch strip under the row, grass alleys with bare soil patches
    s = spec.ground_spacing_m
    gx, gy = np.meshgrid(np.arange(xr[0], xr[1], s), np.arange(-y_half, y_half, s))
    gx = gx.ravel() + rng.uniform(-0.4, 0.4, gx.size) * s
    gy = gy.ravel() + rng.uniform(-0.4, 0.4, gy.size) * s
    gz = ground.height(gx, gy)
    gp = np.column_stack([gx, gy, gz])
    gn = ground.normal(gx, gy)
    soil, grass, mulch = np.array([0.3, 0.22, 0.15]), np.array([0.16, 0.3, 0.09]), np.array([0.5, 0.41, 0.27])
    patch = np.clip(0.5 + 1.5 * _smooth_noise(gp, rng, (0.6, 1.5)), 0, 1)[:, None]
    alley = soil * (1 - patch) + grass * patch
    edge = np.clip((np.abs(gy) - 0.45) / 0.15 + 0.3 * _smooth_noise(gp, rng, (0.2,)), 0, 1)[:, None]
    alb = mulch * (1 - edge) + alley * edge
    alb *= (1 + 0.35 * _smooth_noise(gp, rng, (0.015, 0.05)))[:, None] * rng.uniform(0.7, 1.3, (len(gp), 1))
    parts.append((gp, np.full(len(gp), 0.8 * s), alb, gn, np.full(len(gp), PCls.GROUND, np.uint8),
                  np.full(len(gp), -1, np.int32)))

    # --- neighbouring rows: thinned scan trees (no truth), seen in the background
    if spec.background_row_m > 0:
        for side in (-1.0, 1.0):
            bx = xr[0] + 0.5
            while bx < xr[1]:
                sc = pool[int(rng.integers(len(pool)))]
                sub = sc.points[rng.choice(len(sc.points), min(len(sc.points), 14000), replace=False)]
                sub = sub[sub[:, 2] > 0.02]
                scl = rng.uniform(*spec.height_m) / float(np.percentile(sc.points[:, 2], 99.9))
                Rz = Rotation.from_euler("z", rng.uniform(0, 2 * np.pi)).as_matrix()
                by = side * spec.background_row_m
                p = (sub * scl) @ Rz.T + np.array([bx, by, float(ground.height(np.array(bx), np.array(by))) - 0.01])
                nrm, d3 = _normals(p, 8)
                hax = np.linalg.norm(sub[:, :2] - sc.axis[0, :2], axis=1) * scl
                trunk = (hax < 0.03) & (sub[:, 2] * scl < 0.9)
                alb = np.where(trunk[:, None], [0.27, 0.23, 0.2], [0.1, 0.24, 0.07]) * rng.uniform(
                    0.7, 1.3, (len(p), 1))
                parts.append((p, np.clip(0.8 * d3, 0.002, 0.03), alb, nrm,
                              np.where(trunk, PCls.TRUNK, PCls.FOLIAGE).astype(np.uint8),
                              np.full(len(p), -1, np.int32)))
                bx += rng.uniform(*spec.spacing_m)

    if fruit:
        parts.append(_fruit_points(fruit, np.random.default_rng([seed, _FRUIT_STREAM, 1])))
    cat = [np.concatenate([p[k] for p in parts]) for k in range(6)]
    scene = PointScene(cat[0].astype(np.float32), cat[1].astype(np.float32),
                       np.clip(cat[2], 0, 1).astype(np.float32), cat[3].astype(np.float32), cat[4], cat[5])
    return ScanRowScene(spec, ground, placed, posts, scene, (x0, x1), fruit)
