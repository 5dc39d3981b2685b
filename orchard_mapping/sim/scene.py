"""Procedural orchard row: terrain, trunks, branching canopies, fruit, posts, wire, weeds.

World frame (REP-103): x along the row, y to the left of the row direction, z up; metres.
The whole scene is one triangle mesh with per-triangle class, instance and albedo,
so one ray cast gives depth, colour and instance labels. Everything is drawn
from one seeded generator: the same scenario and seed give the same row.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from orchard_mapping.sim.scenario import Scenario, TrunkSpec


class Cls(IntEnum):
    """Semantic class of a triangle (and of the pixel that sees it)."""

    SKY = 0
    GROUND = 1
    TRUNK = 2
    BRANCH = 3
    LEAF = 4
    FRUIT = 5
    POST = 6
    WIRE = 7
    WEED = 8
    HEDGE = 9


@dataclass
class MeshBuilder:
    """Accumulates triangles with per-triangle attributes."""

    vertices: list[np.ndarray] = field(default_factory=list)
    triangles: list[np.ndarray] = field(default_factory=list)
    cls: list[np.ndarray] = field(default_factory=list)
    inst: list[np.ndarray] = field(default_factory=list)
    albedo: list[np.ndarray] = field(default_factory=list)
    sway: list[np.ndarray] = field(default_factory=list)  # per-vertex wind weight (0 = rigid)
    n_vertices: int = 0
    n_triangles: int = 0

    def add(self, v: np.ndarray, t: np.ndarray, cls: Cls, inst: int | np.ndarray,
            albedo: np.ndarray, sway: np.ndarray | float = 0.0) -> None:
        n_t = len(t)
        self.vertices.append(np.asarray(v, np.float64))
        self.triangles.append(np.asarray(t, np.int64) + self.n_vertices)
        self.cls.append(np.full(n_t, int(cls), np.uint8))
        self.inst.append(np.broadcast_to(np.asarray(inst, np.int32), (n_t,)).copy())
        self.albedo.append(np.broadcast_to(np.asarray(albedo, np.float32), (n_t, 3)).copy())
        self.sway.append(np.broadcast_to(np.asarray(sway, np.float32), (len(v),)).copy())
        self.n_vertices += len(v)
        self.n_triangles += n_t


@dataclass(frozen=True)
class Terrain:
    """Ground height z = h(x, y): slope plus smooth undulation plus fine roughness."""

    slope: float  # dz/dx
    cross: float  # dz/dy
    wave_k: np.ndarray  # (M, 2) rad/m
    wave_a: np.ndarray  # (M,) m
    wave_phase: np.ndarray  # (M,) rad

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        z = self.slope * x + self.cross * y
        arg = x[..., None] * self.wave_k[:, 0] + y[..., None] * self.wave_k[:, 1] + self.wave_phase
        return z + np.sum(self.wave_a * np.sin(arg), axis=-1)


@dataclass(frozen=True)
class TreeGeom:
    """Scene description of one tree (the ground truth is derived from it)."""

    id: int
    base: np.ndarray  # (3,) world, trunk axis at the ground
    axis_points: np.ndarray  # (K, 3) world, trunk/leader centre line from below ground to the top
    axis_s: np.ndarray  # (K,) m, arc length of axis_points from base
    axis_diam: np.ndarray  # (K,) m, diameter at axis_points
    clear_height: float  # m above local ground
    ground_point: np.ndarray  # (3,)
    ground_normal: np.ndarray  # (3,) unit, up
    canopy_points: np.ndarray  # (P, 3) world, samples of leaves, branches, fruit (volume definition)
    top_z_point: np.ndarray  # (3,) highest point of the tree's geometry
    fruit_index: np.ndarray  # (F,) global fruit indices of this tree
    trunk_tri: np.ndarray  # (2,) first/last+1 triangle index of the trunk (clear part + leader)
    leaf_tri: np.ndarray  # (L,) triangle indices of this tree's leaves


@dataclass(frozen=True)
class Fruit:
    tree: int
    position: np.ndarray  # (3,) world centre
    radius: float  # m
    color: str  # "red" / "green"


@dataclass
class Scene:
    scenario: Scenario
    terrain: Terrain
    vertices: np.ndarray  # (V, 3) float64 world, rest positions
    triangles: np.ndarray  # (T, 3) int64
    tri_cls: np.ndarray  # (T,) uint8 Cls
    tri_inst: np.ndarray  # (T,) int32: tree id (trunk/branch/leaf), fruit index, post index, else -1
    tri_albedo: np.ndarray  # (T, 3) float32 in [0, 1]
    vertex_sway: np.ndarray  # (V,) float32 wind weight
    vertex_phase: np.ndarray  # (V,) float32 rad
    trees: list[TreeGeom]
    fruit: list[Fruit]
    posts: list[dict]
    row_x: tuple[float, float]  # x of the first and last trunk (of the first row)
    rows: tuple["RowLine", ...] = ()  # every row of the scene (one, or a block's)


@dataclass(frozen=True)
class RowLine:
    """One row of a scene: its trunk line on y = y (world), from x[0] to x[1] (first and last trunk)."""

    number: int  # 1, 2, ...: the order of the rows along +y
    y: float  # m
    x: tuple[float, float]  # m
    tree_ids: tuple[int, ...]


# ----------------------------------------------------------------------------- primitives

def _frame(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to the unit vectors t (N, 3)."""
    ref = np.where(np.abs(t[:, 2:3]) < 0.9, np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0.0, 0.0]]))
    u = np.cross(t, ref)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(t, u)
    return u, v


def tube(centres: np.ndarray, radii: np.ndarray, segments: int, cap: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Generalised cylinder along a centre line (K, 3) with radii (K,), or (K, segments) for a cross-section
    that is not a circle (angles from the centre line's normal frame): vertices, triangles."""
    k = len(centres)
    tang = np.gradient(centres, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    u, v = _frame(tang)
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring = np.cos(ang)[None, :, None] * u[:, None, :] + np.sin(ang)[None, :, None] * v[:, None, :]  # (K, S, 3)
    r = np.asarray(radii, float)
    r = r[:, None] if r.ndim == 1 else r  # (K, 1) or (K, S)
    verts = centres[:, None, :] + r[:, :, None] * ring
    verts = verts.reshape(-1, 3)
    i = np.arange(k - 1)[:, None]
    j = np.arange(segments)[None, :]
    a = i * segments + j
    b = i * segments + (j + 1) % segments
    c = a + segments
    d = b + segments
    tris = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    if cap:
        top = len(verts)
        verts = np.vstack([verts, centres[-1]])
        jj = np.arange(segments)
        last = (k - 1) * segments
        tris = np.vstack([tris, np.stack([last + jj, last + (jj + 1) % segments, np.full(segments, top)], -1)])
    return verts, tris


def uv_sphere(n_lat: int = 7, n_lon: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere mesh."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    ring = np.stack([np.sin(th)[:, None] * np.cos(ph), np.sin(th)[:, None] * np.sin(ph),
                     np.cos(th)[:, None] * np.ones_like(ph)], -1).reshape(-1, 3)
    verts = np.vstack([[0, 0, 1], ring, [0, 0, -1]])
    tris = []
    j = np.arange(n_lon)
    jn = (j + 1) % n_lon
    tris.append(np.stack([np.zeros(n_lon, int), 1 + j, 1 + jn], -1))
    for r in range(n_lat - 2):
        a = 1 + r * n_lon + j
        b = 1 + r * n_lon + jn
        tris.append(np.stack([a, a + n_lon, b], -1))
        tris.append(np.stack([b, a + n_lon, b + n_lon], -1))
    last = 1 + (n_lat - 2) * n_lon
    tris.append(np.stack([last + j, np.full(n_lon, len(verts) - 1), last + jn], -1))
    return verts, np.vstack(tris)


def grid_mesh(xs: np.ndarray, ys: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Height-field mesh over xs (NX,), ys (NY,) with heights z (NY, NX)."""
    X, Y = np.meshgrid(xs, ys)
    verts = np.stack([X, Y, z], -1).reshape(-1, 3)
    nx = len(xs)
    i, j = np.meshgrid(np.arange(len(ys) - 1), np.arange(nx - 1), indexing="ij")
    a = (i * nx + j).ravel()
    b = a + 1
    c = a + nx
    d = c + 1
    tris = np.concatenate([np.stack([a, b, c], -1), np.stack([b, d, c], -1)])
    return verts, tris


# ----------------------------------------------------------------------------- the row

def _canopy_profile(u: np.ndarray) -> np.ndarray:
    """Relative canopy radius at relative height u in [0, 1] above the clear trunk (tall spindle)."""
    u = np.clip(u, 0.0, 1.0)
    return np.clip(1.15 * (1.0 - u) ** 0.75 * np.minimum(1.0, 0.45 + 2.2 * u), 0.0, 1.0)


_ROW_STREAM = 0x726F77  # the draws of a block's rows after the first: (seed, this, row index)


def _tree_xy(rng: np.random.Generator, row) -> tuple[np.ndarray, np.ndarray]:
    """x (along the row, the first trunk at 0) and y offsets (across it) of a row's trunks."""
    n = row.n_trees
    gaps = row.spacing_m + rng.uniform(-1, 1, n - 1) * row.spacing_jitter_m if n > 1 else np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(gaps)]), rng.uniform(-1, 1, n) * row.offset_jitter_m


def _terrain(rng: np.random.Generator, row) -> Terrain:
    m = 5
    ang = rng.uniform(0, 2 * np.pi, m)
    wl = row.undulation_wavelength_m * rng.uniform(0.7, 1.4, m)
    k_und = np.stack([np.cos(ang), np.sin(ang)], 1) * (2 * np.pi / wl)[:, None]
    a_und = row.undulation_m * rng.uniform(0.4, 1.0, m) / np.sqrt(m / 2)
    m_r = 8
    ang_r = rng.uniform(0, 2 * np.pi, m_r)
    k_r = np.stack([np.cos(ang_r), np.sin(ang_r)], 1) * (2 * np.pi / rng.uniform(0.12, 0.35, m_r))[:, None]
    a_r = row.roughness_m * rng.uniform(0.5, 1.0, m_r) / np.sqrt(m_r / 2)
    return Terrain(
        slope=float(np.tan(np.radians(row.slope_deg))),
        cross=float(np.tan(np.radians(row.cross_slope_deg))),
        wave_k=np.vstack([k_und, k_r]),
        wave_a=np.concatenate([a_und, a_r]),
        wave_phase=rng.uniform(0, 2 * np.pi, m + m_r),
    )


def build_scene(sc: Scenario, seed: int) -> Scene:
    """The scenario's row (or, with block.rows > 1, its block of parallel rows) as one mesh.

    A block's first row is drawn exactly as a row alone is (same seed, same row); each further row, on
    y = k * block.row_spacing_m, draws its trees, posts and weeds from a stream of its own, so that adding a row
    changes none of the others. The ground and the hedges span the whole block."""
    rng = np.random.default_rng(seed)
    row, st, blk = sc.row, sc.structure, sc.block
    mb = MeshBuilder()

    # --- tree positions along each row, the terrain
    row_rngs = [rng] + [np.random.default_rng([seed, _ROW_STREAM, k]) for k in range(1, blk.rows)]
    xy = [_tree_xy(rng, row)]
    terrain = _terrain(rng, row)
    xy += [_tree_xy(r, row) for r in row_rngs[1:]]
    row_y = [k * blk.row_spacing_m for k in range(blk.rows)]
    x_lo = min(float(xs[0]) for xs, _ in xy) - row.margin_m
    x_hi = max(float(xs[-1]) for xs, _ in xy) + row.margin_m
    apron = max(3.0, blk.headland_m + 0.5)  # ground beyond the path's ends (to the headland hedge, if any)
    gx = np.arange(x_lo - apron, x_hi + apron, 0.08)
    gy = np.arange(-st.hedge_distance_m - 0.4, row_y[-1] + st.hedge_distance_m + 0.4, 0.08)
    gz = terrain.height(*np.meshgrid(gx, gy))
    v, t = grid_mesh(gx, gy, gz)
    mb.add(v, t, Cls.GROUND, -1, (0.42, 0.34, 0.24))

    trees: list[TreeGeom] = []
    fruits: list[Fruit] = []
    posts: list[dict] = []
    rows: list[RowLine] = []
    sphere_v, sphere_t = uv_sphere()
    for k, (r_rng, (xs, ys), y0) in enumerate(zip(row_rngs, xy, row_y, strict=True)):
        first = len(trees)
        for i in range(len(xs)):
            # The trunk's cross-section (ellipse, bark) draws from a stream of its own: a row with elliptical
            # trunks is otherwise the same row (same canopies, fruit, weeds), so the two compare tree by tree.
            tid = len(trees)
            shape_rng = np.random.default_rng([seed, _TRUNK_SHAPE_STREAM, tid])
            trees.append(_build_tree(mb, r_rng, sc, tid, np.array([xs[i], y0 + ys[i]]), terrain, fruits, sphere_v,
                                     sphere_t, shape_rng, seed))
        _posts_and_wires(mb, r_rng, sc, xs, y0, terrain, posts)
        _weeds(mb, r_rng, sc, float(xs[0]), float(xs[-1]), y0, terrain)
        rows.append(RowLine(k + 1, y0, (float(xs[0]), float(xs[-1])), tuple(range(first, len(trees)))))

    # --- neighbouring rows as hedges in the background (depth and features at 3-6 m), beyond the outer rows
    x0, x1 = float(xy[0][0][0]), float(xy[0][0][-1])
    hx = np.arange(x0 - row.margin_m - 3.0, x1 + row.margin_m + 3.0, 0.15)
    if blk.rows > 1:
        hx = np.arange(x_lo - apron, x_hi + apron, 0.15)
    hz = np.arange(0.0, st.hedge_height_m, 0.15)
    def hedge_wall(along: np.ndarray, across: float, along_x: bool) -> None:
        # a wall of foliage on the grid along x hz, `across` m away on the other axis, leaves jittered 5 cm
        A, HZ = np.meshgrid(along, hz)
        C = across + rng.normal(0, 0.05, A.shape) * (HZ > 0.3)
        HX, HY = (A, C) if along_x else (C, A)
        verts = np.stack([HX, HY, HZ + terrain.height(HX, HY)], -1).reshape(-1, 3)
        _, t = grid_mesh(along, hz, np.zeros((len(hz), len(along))))
        alb = np.array(sc.appearance.hedge_rgb) * rng.uniform(*sc.appearance.hedge_gain, (len(t), 1))
        mb.add(verts, t, Cls.HEDGE, -1, alb)

    for hy in (-st.hedge_distance_m, row_y[-1] + st.hedge_distance_m):
        hedge_wall(hx, hy, along_x=True)
    if blk.headland_m > 0:
        # across both ends of the block, headland_m beyond the path's ends: what a turn in the headland looks at
        hy = np.arange(-st.hedge_distance_m, row_y[-1] + st.hedge_distance_m, 0.15)
        for hx0 in (x_lo - blk.headland_m, x_hi + blk.headland_m):
            hedge_wall(hy, hx0, along_x=False)

    vertices = np.concatenate(mb.vertices)
    sway = np.concatenate(mb.sway)
    return Scene(
        scenario=sc,
        terrain=terrain,
        vertices=vertices,
        triangles=np.concatenate(mb.triangles),
        tri_cls=np.concatenate(mb.cls),
        tri_inst=np.concatenate(mb.inst),
        tri_albedo=np.concatenate(mb.albedo),
        vertex_sway=sway,
        vertex_phase=rng.uniform(0, 2 * np.pi, len(vertices)).astype(np.float32),
        trees=trees,
        fruit=fruits,
        posts=posts,
        row_x=rows[0].x,
        rows=tuple(rows),
    )


def _posts_and_wires(mb: MeshBuilder, rng: np.random.Generator, sc: Scenario, xs: np.ndarray, y0: float,
                     terrain: Terrain, posts: list[dict]) -> None:
    """A row's trellis (on y = y0): end posts, a post every post_every_n_trees trees, the wires between the end
    posts. Post ids run on over the block's rows (the instance masks' post index)."""
    row, st, ap = sc.row, sc.structure, sc.appearance
    n = len(xs)
    x0, x1 = float(xs[0]), float(xs[-1])
    post_x = [x0 - 0.5 * row.spacing_m, x1 + 0.5 * row.spacing_m]
    if st.post_every_n_trees > 0:
        post_x += [0.5 * (xs[k] + xs[k + 1]) for k in range(st.post_every_n_trees - 1, n - 1, st.post_every_n_trees)]
    for px in sorted(post_x):
        pz = float(terrain.height(px, y0))
        s = np.linspace(-0.2, st.post_height_m, 30)
        c = np.stack([np.full_like(s, px), np.full_like(s, y0), pz + s], 1)
        v, t = tube(c, np.full(len(s), st.post_diameter_m / 2), 16)
        mb.add(v, t, Cls.POST, len(posts), np.array(ap.post_rgb) * rng.uniform(*ap.post_gain))
        posts.append({"position": [px, y0, pz], "diameter_m": st.post_diameter_m, "height_m": st.post_height_m})
    pxs = sorted(post_x)
    for h in st.wire_heights_m:
        wx = np.linspace(pxs[0], pxs[-1], 60)
        zb = terrain.height(np.array([pxs[0], pxs[-1]]), np.full(2, y0))
        wz = np.interp(wx, [pxs[0], pxs[-1]], zb) + h
        c = np.stack([wx, np.zeros_like(wx) + y0 - st.post_diameter_m / 2, wz], 1)
        v, t = tube(c, np.full(len(wx), st.wire_diameter_m / 2), 6, cap=False)
        mb.add(v, t, Cls.WIRE, -1, (0.6, 0.6, 0.62))


def _weeds(mb: MeshBuilder, rng: np.random.Generator, sc: Scenario, x0: float, x1: float, y0: float,
           terrain: Terrain) -> None:
    """Clumps of blades under and beside a row (on y = y0)."""
    row, st, ap = sc.row, sc.structure, sc.appearance
    area_x = (x1 - x0) + 2 * row.margin_m + 2.0
    n_clumps = rng.poisson(st.weeds_per_m2 * area_x * 1.6 / 5.0)
    if not n_clumps:
        return
    cx = rng.uniform(x0 - row.margin_m - 1.0, x1 + row.margin_m + 1.0, n_clumps)
    cy = y0 + rng.uniform(-0.8, 0.8, n_clumps)
    bx = (cx[:, None] + rng.normal(0, 0.04, (n_clumps, 5))).ravel()
    by = (cy[:, None] + rng.normal(0, 0.04, (n_clumps, 5))).ravel()
    bz = terrain.height(bx, by) - 0.01
    hgt = rng.uniform(*st.weed_height_m, len(bx))
    phi = rng.uniform(0, np.pi, len(bx))
    lean = rng.normal(0, 0.3, (len(bx), 2)) * hgt[:, None]
    w = 0.012
    p0 = np.stack([bx - w * np.cos(phi), by - w * np.sin(phi), bz], 1)
    p1 = np.stack([bx + w * np.cos(phi), by + w * np.sin(phi), bz], 1)
    p2 = np.stack([bx + lean[:, 0], by + lean[:, 1], bz + hgt], 1)
    v = np.stack([p0, p1, p2], 1).reshape(-1, 3)
    t = np.arange(len(v)).reshape(-1, 3)
    alb = np.array(ap.weed_rgb) * rng.uniform(*ap.weed_gain, (len(t), 1))
    mb.add(v, t, Cls.WEED, -1, alb, sway=np.tile([0.0, 0.0, 0.3], len(t)))


def local_ground_plane(terrain: Terrain, x: float, y: float, radius: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane of the terrain within `radius` of (x, y): point under (x, y), unit up normal.

    This is the definition of a tree's local ground in the ground truth.
    """
    r = np.sqrt(np.linspace(0, 1, 12))[1:] * radius
    a = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    px = np.concatenate([[x], (x + r[:, None] * np.cos(a)).ravel()])
    py = np.concatenate([[y], (y + r[:, None] * np.sin(a)).ravel()])
    return terrain_plane(terrain, px, py, x, y)


def terrain_plane(terrain: Terrain, px: np.ndarray, py: np.ndarray, x: float, y: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares plane z = gx (x' - x) + gy (y' - y) + c of the terrain heights at (px, py) (N,):
    its point under (x, y) and its unit up normal."""
    pz = terrain.height(px, py)
    A = np.stack([px - x, py - y, np.ones_like(px)], 1)
    (gx, gy, c), *_ = np.linalg.lstsq(A, pz, rcond=None)
    normal = np.array([-gx, -gy, 1.0])
    normal /= np.linalg.norm(normal)
    return np.array([x, y, c]), normal


TRUNK_SEGMENTS = 20  # vertices around the trunk's cross-section
_TRUNK_SHAPE_STREAM = 0x7472756E  # the trunks' cross-section draws (seed, this, tree)
_FRUIT_LOOK_STREAM = 0x66727574  # the varied fruit look's draws (seed, this, fruit index)
# Varied fruit look (FruitSpec.look): ground colours (grass green, yellow-green, golden) and blush colours
# (deep red, red, pink-red, orange-red), albedo in [0, 1].
_FRUIT_GROUND = np.array([[0.45, 0.68, 0.18], [0.62, 0.70, 0.24], [0.82, 0.74, 0.32]])
_FRUIT_BLUSH = np.array([[0.50, 0.05, 0.05], [0.74, 0.11, 0.08], [0.78, 0.34, 0.30], [0.80, 0.30, 0.10]])


def varied_fruit_albedo(rng: np.random.Generator, red: bool, sphere_v: np.ndarray, sphere_t: np.ndarray
                        ) -> np.ndarray:
    """(T, 3) per-triangle albedo of one fruit of the varied look: a ground colour, a blush over part of the
    fruit (most of a red fruit, a faint cheek on some green ones) facing a random, mostly upward side, with a
    soft edge, streaks along the meridians and speckle. The sphere's axis is the stem's (z)."""
    c = sphere_v[sphere_t].mean(axis=1)  # (T, 3) triangle centres on the unit sphere
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    w_g = rng.dirichlet(np.ones(len(_FRUIT_GROUND)))
    ground = w_g @ _FRUIT_GROUND  # (3,)
    w_b = rng.dirichlet(np.full(len(_FRUIT_BLUSH), 0.5))
    blush = w_b @ _FRUIT_BLUSH
    if red:
        cover = rng.uniform(0.3, 1.0)  # share of the surface blushed
    else:
        cover = rng.uniform(0.0, 0.25) if rng.uniform() < 0.4 else 0.0
    d = rng.standard_normal(3) + np.array([0.0, 0.0, 0.7])
    d /= np.linalg.norm(d)
    soft = rng.uniform(0.1, 0.4)
    # the cap of the sphere whose area share is `cover` is the side where c . d > 1 - 2 cover
    w = np.clip((c @ d - (1.0 - 2.0 * cover)) / soft * 0.5 + 0.5, 0.0, 1.0) * (cover > 0)
    if rng.uniform() < 0.5:  # streaks: the blush broken along the meridians
        lon = np.arctan2(c[:, 1], c[:, 0])
        k = int(rng.integers(5, 12))
        w = w * (1.0 - rng.uniform(0.2, 0.7) * (0.5 + 0.5 * np.sin(k * lon + rng.uniform(0, 2 * np.pi))))
    alb = ground[None] * (1 - w[:, None]) + blush[None] * w[:, None]
    alb = alb * rng.uniform(0.75, 1.15) * (1.0 + rng.normal(0.0, 0.04, (len(c), 1)))
    return np.clip(alb, 0.0, 1.0)


def trunk_radii(rng: np.random.Generator, tr: TrunkSpec, s: np.ndarray, r_mean: np.ndarray, segments: int
                ) -> np.ndarray:
    """Radii of the trunk mesh: (K,) a circle of r_mean (m) at each axis point, or (K, segments) where
    the trunk is elliptical or its bark rough. An ellipse of semi-axes r (1 + e) and r (1 - e), its major
    axis turned at random, keeps the stated diameter as the mean of its two axes (two caliper readings
    at right angles); the bark's bumps are a few smooth waves round and along the trunk. rng: the trunk's
    own stream (build_scene), so the rest of the scene does not change with these settings."""
    if max(tr.ellipticity) <= 0 and tr.bark_roughness_m <= 0:
        return r_mean
    ang = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)  # (S,)
    e = rng.uniform(*tr.ellipticity)
    theta = rng.uniform(0.0, np.pi)
    unit = 1.0 / np.sqrt((np.cos(ang - theta) / (1 + e)) ** 2 + (np.sin(ang - theta) / (1 - e)) ** 2)  # (S,)
    radii = r_mean[:, None] * unit[None, :]  # (K, S)
    if tr.bark_roughness_m > 0:
        waves = 6
        m = rng.integers(2, 7, waves)  # waves round the trunk
        k = 2 * np.pi / rng.uniform(0.05, 0.3, waves)  # rad/m along it
        phase = rng.uniform(0, 2 * np.pi, waves)
        bumps = np.cos(m[None, None, :] * ang[None, :, None] + k[None, None, :] * s[:, None, None] + phase).sum(-1)
        radii = radii + tr.bark_roughness_m * bumps / np.sqrt(waves / 2)  # sd of a sum of unit cosines
    return radii


def _build_tree(mb: MeshBuilder, rng: np.random.Generator, sc: Scenario, tid: int, xy: np.ndarray,
                terrain: Terrain, fruits: list[Fruit], sphere_v: np.ndarray, sphere_t: np.ndarray,
                shape_rng: np.random.Generator, seed: int) -> TreeGeom:
    tr, cp, fr = sc.trunk, sc.canopy, sc.fruit
    gp, gn = local_ground_plane(terrain, float(xy[0]), float(xy[1]))
    base = np.array([xy[0], xy[1], float(terrain.height(xy[0], xy[1]))])
    height = rng.uniform(*cp.height_m)
    clear = rng.uniform(*tr.clear_height_m)
    d_stated = float(np.clip(rng.normal(tr.diameter_mean_m, tr.diameter_sd_m), tr.diameter_min_m, tr.diameter_max_m))

    # Centre line: lean in a random direction plus a gentle bow; the leader ends below the top.
    lean = np.radians(rng.uniform(0, tr.lean_deg_max))
    az = rng.uniform(0, 2 * np.pi)
    lean_dir = np.array([np.sin(lean) * np.cos(az), np.sin(lean) * np.sin(az), np.cos(lean)])
    bow_az = rng.uniform(0, 2 * np.pi)
    bow_dir = np.array([np.cos(bow_az), np.sin(bow_az), 0.0])
    leader_len = 0.85 * height
    s = np.concatenate([np.arange(-0.12, clear + 0.1, 0.02), np.arange(clear + 0.1, leader_len, 0.05)])
    axis = base + s[:, None] * lean_dir + (tr.curve_m * np.sin(np.pi * np.clip(s, 0, None) / leader_len))[:, None] * bow_dir
    # Diameter: linear taper through the stated height, then thinning along the leader.
    h_axis = (axis - gp) @ gn  # height of axis points above the local ground plane
    s_stated = float(np.interp(tr.diameter_height_m, h_axis, s))
    d_lin = d_stated + tr.taper_per_m * (s_stated - s)
    s_clear = float(np.interp(clear, h_axis, s))
    d_clear = d_stated + tr.taper_per_m * (s_stated - s_clear)
    frac = np.clip((s - s_clear) / (leader_len - s_clear), 0, 1)
    diam = np.where(s <= s_clear, d_lin, d_clear * (1 - 0.8 * frac ** 0.8))
    v, t = tube(axis, trunk_radii(shape_rng, tr, s, diam / 2, TRUNK_SEGMENTS), TRUNK_SEGMENTS)
    t0 = mb.n_triangles
    ap = sc.appearance
    bark = np.array(ap.bark_rgb) * rng.uniform(*ap.bark_gain)
    mb.add(v, t, Cls.TRUNK, tid, bark)
    trunk_tri = np.array([t0, t0 + len(t)])

    # Canopy envelope: ellipse radii along / across the row, scaled by the height profile.
    ra = rng.uniform(*cp.radius_along_row_m)
    rc = rng.uniform(*cp.radius_across_row_m)
    z_clear = clear
    canopy_pts = [axis[s > s_clear]]

    def leader_at(hh: np.ndarray) -> np.ndarray:
        return axis[np.clip(np.searchsorted(h_axis, hh), 0, len(axis) - 1)]

    def envelope_r(hh: np.ndarray, phi: np.ndarray) -> np.ndarray:
        u = (hh - z_clear) / (height - z_clear)
        return _canopy_profile(u) / np.sqrt((np.cos(phi) / ra) ** 2 + (np.sin(phi) / rc) ** 2)

    # Branches from the leader out to the envelope.
    nb = rng.integers(cp.branches[0], cp.branches[1] + 1)
    bh = np.sort(rng.uniform(z_clear + 0.02, 0.88 * height, nb))
    bphi = rng.uniform(0, 2 * np.pi, nb)
    branch_lines = []
    for hb, ph in zip(bh, bphi, strict=True):
        start = leader_at(np.array([hb]))[0]
        length = float(envelope_r(np.array([hb]), np.array([ph]))[0]) * rng.uniform(0.75, 1.0)
        if length < 0.08:
            continue
        rise = np.radians(rng.uniform(5, 35))
        q = np.linspace(0, 1, 6)
        dirh = np.array([np.cos(ph), np.sin(ph), 0.0])
        c = (start + (q * length * np.cos(rise))[:, None] * dirh
             + (q * length * np.sin(rise) - 0.12 * length * q ** 2)[:, None] * np.array([0, 0, 1.0]))
        rb = rng.uniform(0.006, 0.012) * (1 - 0.7 * q)
        v, t = tube(c, rb, 6)
        mb.add(v, t, Cls.BRANCH, tid, bark * 0.95, sway=np.repeat(q, 6).tolist() + [1.0])
        branch_lines.append(c)
        canopy_pts.append(c)

    # Leaves: clustered around branch and leader points, kept inside the envelope.
    env_vol = 0.0
    hs = np.linspace(z_clear, height, 40)
    env_vol = float(np.sum(np.pi * ra * rc * _canopy_profile((hs - z_clear) / (height - z_clear)) ** 2) * (hs[1] - hs[0]))
    n_leaves = int(cp.leaves_per_m3 * env_vol)
    anchors = np.vstack(branch_lines + [axis[s > s_clear + 0.1]])
    pick = anchors[rng.integers(0, len(anchors), n_leaves)]
    pos = pick + rng.normal(0, 1, (n_leaves, 3)) * np.array([0.09, 0.09, 0.07])
    # Top leaves: the highest point of the tree is at `height` above local ground.
    top_c = leader_at(np.array([height * 0.85]))[0]
    n_top = max(8, n_leaves // 60)
    top_pos = top_c + np.stack([rng.normal(0, 0.05, n_top), rng.normal(0, 0.05, n_top),
                                rng.uniform(0, 0.15 * height, n_top)], 1)
    pos = np.vstack([pos, top_pos])
    hh = (pos - gp) @ gn
    rel = pos[:, :2] - leader_at(hh)[:, :2]
    phi = np.arctan2(rel[:, 1], rel[:, 0])
    keep = (np.linalg.norm(rel, axis=1) <= 1.05 * envelope_r(hh, phi) + 0.02) & (hh > z_clear + 0.03) & (hh < height - 0.03)
    pos = pos[keep]
    nl = len(pos)
    size = rng.uniform(*cp.leaf_size_m, nl)
    nrm = rng.normal(0, 1, (nl, 3)) + np.array([0, 0, 1.2])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    u, w = _frame(nrm)
    # Leaf as a diamond (2 triangles): tip, side, base, side.
    p_tip = pos + u * (size / 2)[:, None]
    p_base = pos - u * (size / 2)[:, None]
    p_l = pos + w * (size / 4)[:, None]
    p_r = pos - w * (size / 4)[:, None]
    v = np.stack([p_tip, p_l, p_base, p_r], 1).reshape(-1, 3)
    b = np.arange(nl)[:, None] * 4
    t = np.concatenate([b + np.array([0, 1, 2]), b + np.array([0, 2, 3])], 1).reshape(-1, 3)
    hue = rng.uniform(0, 1, (nl, 1))
    alb = (np.array(ap.leaf_rgb_a) * (1 - hue) + np.array(ap.leaf_rgb_b) * hue) * rng.uniform(*ap.leaf_gain, (nl, 1))
    alb = np.repeat(alb, 2, axis=0)
    t_leaf0 = mb.n_triangles
    radial = np.linalg.norm(rel[keep], axis=1) / np.maximum(envelope_r(hh[keep], phi[keep]), 0.05)
    mb.add(v, t, Cls.LEAF, tid, alb, sway=np.repeat(np.clip(radial, 0.2, 1.0), 4))
    leaf_tri = np.arange(t_leaf0, t_leaf0 + len(t))
    canopy_pts.append(v)

    # Fruit: hanging in the outer canopy, some deep inside.
    nf = rng.integers(fr.per_tree[0], fr.per_tree[1] + 1)
    f_idx = []
    for _ in range(nf):
        for _try in range(20):
            hf = rng.uniform(z_clear + 0.08, z_clear + 0.85 * (height - z_clear))
            ph = rng.uniform(0, 2 * np.pi)
            rmax = float(envelope_r(np.array([hf]), np.array([ph]))[0])
            if rmax > 0.1:
                break
        rf = rng.uniform(*fr.radius_m)
        radial = rmax * np.sqrt(rng.uniform(0.1, 1.0)) * 0.92
        centre = leader_at(np.array([hf]))[0] + np.array([radial * np.cos(ph), radial * np.sin(ph), 0.0])
        red = rng.uniform() < fr.red_fraction
        color = np.array([0.72, 0.09, 0.07]) if red else np.array([0.5, 0.72, 0.2])
        color = color * rng.uniform(0.85, 1.1)
        gi = len(fruits)
        if fr.look == "varied":
            color = varied_fruit_albedo(np.random.default_rng([seed, _FRUIT_LOOK_STREAM, gi]), red, sphere_v, sphere_t)
        mb.add(centre + rf * sphere_v, sphere_t, Cls.FRUIT, gi, color, sway=0.7)
        fruits.append(Fruit(tid, centre, float(rf), "red" if red else "green"))
        f_idx.append(gi)
        canopy_pts.append(centre + rf * sphere_v)

    pts = np.vstack(canopy_pts)
    hts = (pts - gp) @ gn
    top = pts[np.argmax(hts)]
    return TreeGeom(
        id=tid, base=base, axis_points=axis, axis_s=s, axis_diam=diam, clear_height=float(clear),
        ground_point=gp, ground_normal=gn, canopy_points=pts[hts > z_clear - 0.05],
        top_z_point=top, fruit_index=np.array(f_idx, int), trunk_tri=trunk_tri, leaf_tri=leaf_tri,
    )
