"""Ground truth from the scene description: trait definitions and per-side visibility.

Nothing here calls an estimator of `core/` (a shared bug would hide itself). The canopy volume is a
definition, not an estimate: the alpha-complex volume of `core.canopy`, the one the product measures with,
proved against analytic solids by its own tests.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from orchard_mapping.core.canopy import alpha_complex_volume as alpha_complex_volume  # re-exported: sim.simulate
from orchard_mapping.core.types import CameraIntrinsics
from orchard_mapping.eval.segmentation import TREE_SURFACES_NPZ as TREE_SURFACES_NPZ  # re-exported: sim.simulate
from orchard_mapping.sim.render import RenderOutput
from orchard_mapping.sim.scene import Cls, Scene, TreeGeom, terrain_plane

CANOPY_VOLUME_DEFINITION = (
    "Volume (m^3) of the alpha complex with alpha = {alpha} m of points sampled on the tree's own canopy "
    "geometry (leaf vertices, branch and leader centre lines above the clear trunk, fruit surface vertices): "
    "the union of the Delaunay tetrahedra whose circumradius is below alpha (Edelsbrunner & Muecke 1994), "
    "the paper's alpha-shape canopy volume. Neighbouring trees' geometry is not included."
)
HEIGHT_DEFINITION = (
    "Distance (m) from the tree's local ground plane (least-squares plane of the terrain within 0.5 m of the "
    "trunk) to the tree's highest point, along the plane normal (the paper's bounding box from local ground to top)."
)
DIAMETER_DEFINITION = (
    "Trunk diameter (m) perpendicular to the trunk axis at diameter_height_m above the local ground plane."
)

# A fruit counts as visible from a side when, in at least one frame, at least this share of its projected
# disc and this many pixels are unoccluded.
FRUIT_MIN_VISIBLE_FRACTION = 0.25
FRUIT_MIN_PIXELS = 20
TRUNK_MIN_PIXELS = 50  # trunk pixels within +-5 cm of the diameter height in one frame
TOP_BAND_M = 0.10  # "top seen": any pixel of the tree within this distance of its top
# The local ground a side saw: terrain cells (GROUND_CELL_M square) within LOCAL_GROUND_RADIUS_M of the trunk
# hit by a pixel of that side at depth at most GROUND_SEEN_MAX_RANGE_M (well inside a depth camera's reliable
# range: a RealSense D435's ideal range ends at 3 m, where one pixel's depth noise is ~3.6 cm; ground seen
# only farther is not measured, just glimpsed) in at least GROUND_MIN_FRAMES frames (a glimpse through a gap
# in the leaves is not a measurement); the plane of the terrain over them needs GROUND_MIN_CELLS of them.
GROUND_SEEN_MAX_RANGE_M = 2.5
LOCAL_GROUND_RADIUS_M = 0.5
GROUND_CELL_M = 0.02
GROUND_MIN_CELLS = 50
GROUND_MIN_FRAMES = 5


def trunk_axis_at_height(tree: TreeGeom, h: float) -> np.ndarray:
    """Axis point (3,) at height h above the local ground plane."""
    hs = (tree.axis_points - tree.ground_point) @ tree.ground_normal
    return np.array([np.interp(h, hs, tree.axis_points[:, k]) for k in range(3)])


def diameter_at_height(tree: TreeGeom, h: float) -> float:
    hs = (tree.axis_points - tree.ground_point) @ tree.ground_normal
    return float(np.interp(h, hs, tree.axis_diam))


def fruit_disc_fraction(counts: np.ndarray, fruit_pos: np.ndarray, fruit_r: np.ndarray, T_world_cam: np.ndarray,
                        fx: float) -> np.ndarray:
    """(F,) share of each fruit's projected disc that its counts (F,) visible pixels cover in one frame (0 for a
    fruit within 0.1 m of the camera plane or behind it); fruit_pos (F, 3) world, fruit_r (F,) m."""
    Tcw = np.linalg.inv(T_world_cam)
    pc = fruit_pos @ Tcw[:3, :3].T + Tcw[:3, 3]
    z = np.maximum(pc[:, 2], 1e-3)
    area = np.pi * (fx * fruit_r / z) ** 2
    return np.where(pc[:, 2] > 0.1, counts / area, 0.0)


def fruit_visible(frac: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(F,) bool: the frame shows enough of each fruit for it to count as visible from the side."""
    return (frac >= FRUIT_MIN_VISIBLE_FRACTION) & (counts >= FRUIT_MIN_PIXELS)


class VisibilityAccumulator:
    """What one side's frames saw of each tree, fruit and leaf (from the renderer's instance labels)."""

    def __init__(self, scene: Scene, intr: CameraIntrinsics, diameter_height: float) -> None:
        self.scene = scene
        self.K = intr
        n_f = len(scene.fruit)
        n_t = len(scene.trees)
        self.fruit_tree = np.array([f.tree for f in scene.fruit], np.int32)
        self.fruit_pos = np.array([f.position for f in scene.fruit]).reshape(n_f, 3)
        self.fruit_r = np.array([f.radius for f in scene.fruit])
        self.fruit_best = np.zeros(n_f)  # best visible fraction of the projected disc
        self.fruit_px = np.zeros(n_f, np.int64)  # pixels in that frame
        self.fruit_seen = np.zeros(n_f, bool)
        self.trunk_px = np.zeros(n_t, np.int64)
        self.top_seen = np.zeros(n_t, bool)
        self.tri_seen = np.zeros(len(scene.triangles), bool)
        self.gp = np.array([t.ground_point for t in scene.trees])
        self.gn = np.array([t.ground_normal for t in scene.trees])
        self.height = np.array([tree_height(t) for t in scene.trees])
        self.dh = diameter_height
        n_c = int(round(2 * LOCAL_GROUND_RADIUS_M / GROUND_CELL_M))
        self.ground_cells = np.zeros((n_t, n_c, n_c), np.int32)  # per tree: frames that saw each terrain cell

    def add(self, out: RenderOutput, T_world_cam: np.ndarray) -> None:
        cls = out.cls.ravel()
        inst = out.inst.ravel()
        near_ground = (cls == Cls.GROUND) & (out.depth.ravel() > 0) & (out.depth.ravel() <= GROUND_SEEN_MAX_RANGE_M)
        self._add_ground(out.points.reshape(-1, 3)[near_ground])
        self.tri_seen[out.tri.ravel()[out.tri.ravel() >= 0]] = True
        # Fruit: visible pixels over the projected disc area.
        fr = cls == Cls.FRUIT
        if len(self.fruit_pos):
            counts = np.bincount(inst[fr], minlength=len(self.fruit_pos))
            frac = fruit_disc_fraction(counts, self.fruit_pos, self.fruit_r, T_world_cam, self.K.fx)
            better = frac > self.fruit_best
            self.fruit_best = np.where(better, frac, self.fruit_best)
            self.fruit_px = np.where(better, counts, self.fruit_px)
            self.fruit_seen |= fruit_visible(frac, counts)
        # Per-pixel tree id and height above that tree's local ground.
        tree_cls = (cls == Cls.TRUNK) | (cls == Cls.BRANCH) | (cls == Cls.LEAF) | fr
        # a fruit pixel's instance is its fruit, any other's its tree: look fruit up where there is fruit only
        # (a row with fewer fruit than trees indexed past the fruit table)
        tree = inst.copy()
        tree[fr] = self.fruit_tree[inst[fr]] if len(self.fruit_tree) else -1
        sel = tree_cls & (tree >= 0)
        if not sel.any():
            return
        pts = out.points.reshape(-1, 3)[sel]
        tid = tree[sel]
        h = np.sum((pts - self.gp[tid]) * self.gn[tid], axis=1)
        trunk_band = (cls[sel] == Cls.TRUNK) & (np.abs(h - self.dh) < 0.05)
        self.trunk_px = np.maximum(self.trunk_px, np.bincount(tid[trunk_band], minlength=len(self.trunk_px)))
        top = h >= self.height[tid] - TOP_BAND_M
        self.top_seen[np.unique(tid[top])] = True

    def _add_ground(self, pts: np.ndarray, cells: np.ndarray | None = None) -> None:
        """Mark the terrain cells around each tree that these ground hit points (N, 3) fall in: in `cells`
        (T, C, C) frame counts, the side's own ground_cells unless given."""
        cells = self.ground_cells if cells is None else cells
        n_c = cells.shape[1]
        # Points sorted along the row's longer horizontal axis: each tree then looks only at the slice within
        # the radius along that axis (a whole-frame pass per tree took 8 ms a tree at 640x480).
        axis = int(np.argmax(np.ptp(self.gp[:, :2], axis=0))) if len(self.gp) > 1 else 0
        order = np.argsort(pts[:, axis], kind="stable")
        along = pts[order, axis]
        lo = np.searchsorted(along, self.gp[:, axis] - LOCAL_GROUND_RADIUS_M, side="left")
        hi = np.searchsorted(along, self.gp[:, axis] + LOCAL_GROUND_RADIUS_M, side="right")
        for t in range(len(self.gp)):
            if hi[t] <= lo[t]:
                continue
            d = pts[order[lo[t]:hi[t]], :2] - self.gp[t, :2]  # (n, 2)
            d = d[np.abs(d).max(axis=1) < LOCAL_GROUND_RADIUS_M]
            d = d[np.sum(d**2, axis=1) < LOCAL_GROUND_RADIUS_M**2]
            if not len(d):
                continue
            ij = np.unique(np.clip(((d + LOCAL_GROUND_RADIUS_M) / GROUND_CELL_M).astype(int), 0, n_c - 1), axis=0)
            cells[t, ij[:, 0], ij[:, 1]] += 1

    def seen_ground_plane(self, tree: TreeGeom, cells: np.ndarray | None = None,
                          min_frames: int = GROUND_MIN_FRAMES) -> tuple[np.ndarray, np.ndarray, int] | None:
        """(point under the trunk (3,), unit up normal (3,), cells used): the least-squares terrain plane over
        the cells of the tree's local ground seen in at least `min_frames` frames (counts `cells` (T, C, C),
        the side's own ground_cells unless given); None with fewer than GROUND_MIN_CELLS such cells."""
        cells = self.ground_cells if cells is None else cells
        i, j = np.nonzero(cells[tree.id] >= min_frames)
        if len(i) < GROUND_MIN_CELLS:
            return None
        x = tree.ground_point[0] - LOCAL_GROUND_RADIUS_M + (i + 0.5) * GROUND_CELL_M
        y = tree.ground_point[1] - LOCAL_GROUND_RADIUS_M + (j + 0.5) * GROUND_CELL_M
        point, n = terrain_plane(self.scene.terrain, x, y, float(tree.ground_point[0]), float(tree.ground_point[1]))
        return point, n, len(i)

    def seen_local_ground(self, tree: TreeGeom) -> dict | None:
        """The least-squares terrain plane over the cells of the tree's local ground this side saw."""
        plane = self.seen_ground_plane(tree)
        if plane is None:
            return None
        point, n, used = plane
        disk = np.pi * LOCAL_GROUND_RADIUS_M**2 / GROUND_CELL_M**2
        return {"point": np.round(point, 5).tolist(), "normal": np.round(n, 6).tolist(),
                "seen_fraction": round(min(1.0, used / disk), 4)}

    def summary(self, tree: TreeGeom) -> dict:
        leaves = tree.leaf_tri
        return {
            "trunk_at_diameter_height": bool(self.trunk_px[tree.id] >= TRUNK_MIN_PIXELS),
            "top": bool(self.top_seen[tree.id]),
            "canopy_fraction": round(float(self.tri_seen[leaves].mean()) if len(leaves) else 0.0, 4),
            "local_ground": self.seen_local_ground(tree),
        }


def tree_height(tree: TreeGeom) -> float:
    return float((tree.top_z_point - tree.ground_point) @ tree.ground_normal)


# Per-point segmentation truth: every surface near the row (the trees' trunks, branches, leaves and fruit with
# their tree id; ground, posts, wires and weeds as -1) as points, so that the evaluator can give each
# reconstructed point the surface it lies on. Triangle corners and centres, plus area samples on triangles
# larger than SURFACE_SAMPLE_M squared: a leaf (5-8 cm) keeps its corners and centre, a post or the terrain
# (long, large triangles) gets a sample every ~3 cm, so a point is never nearest a far-off corner.
SURFACE_SAMPLE_M = 0.03
_TREE_PARTS = (Cls.TRUNK, Cls.BRANCH, Cls.LEAF)
_OTHER_PARTS = (Cls.GROUND, Cls.POST, Cls.WIRE, Cls.WEED)  # hedges (the next rows) and sky left out


def tree_surface_samples(scene: Scene, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 world points on the row's surfaces (rest positions) and (N,) int16: the tree id of each,
    -1 where the surface is not a tree's (ground, post, wire, weed)."""
    owner = np.full(len(scene.triangles), -2, dtype=np.int64)  # (T,) -2: not sampled
    part = np.isin(scene.tri_cls, [int(c) for c in _TREE_PARTS])
    owner[part] = scene.tri_inst[part]
    fruit = scene.tri_cls == int(Cls.FRUIT)
    fruit_tree = np.array([f.tree for f in scene.fruit] + [-1], dtype=np.int64)  # (F + 1,)
    owner[fruit] = fruit_tree[scene.tri_inst[fruit]]
    owner[np.isin(scene.tri_cls, [int(c) for c in _OTHER_PARTS])] = -1
    keep = owner >= -1
    tris, own = scene.triangles[keep], owner[keep]  # (K, 3), (K,)
    corners = scene.vertices[tris]  # (K, 3, 3)
    # each vertex belongs to one mesh part: the first triangle that uses it names its owner
    v_ids, first = np.unique(tris.ravel(), return_index=True)
    v_owner = np.repeat(own, 3)[first]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    n_extra = np.floor(area / SURFACE_SAMPLE_M**2).astype(np.int64)  # (K,)
    rng = np.random.default_rng(seed)
    which = np.repeat(np.arange(len(tris)), n_extra)  # (E,)
    u, v = rng.random((2, len(which)))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    c = corners[which]
    extra = c[:, 0] + u[:, None] * (c[:, 1] - c[:, 0]) + v[:, None] * (c[:, 2] - c[:, 0])  # (E, 3)
    pts = np.concatenate([scene.vertices[v_ids], corners.mean(axis=1), extra]).astype(np.float32)
    return pts, np.concatenate([v_owner, own, own[which]]).astype(np.int16)


def write_tree_surfaces(scene: Scene, path: Path) -> None:
    """The surface samples as a compressed npz (points, tree), written atomically."""
    pts, tree = tree_surface_samples(scene)
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, points=pts, tree=tree)
    tmp.replace(path)
