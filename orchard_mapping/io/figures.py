"""row.png: the row from the top and from the front, before and after the side merge; trees/<id>.png: one
tree's segmented points (docs/results.md).

Drawn in the front side's canonical frame of the initial alignment (X along the row, Y up, Z depth
towards the back side), so that the row reads left to right whatever the camera's frames were.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["RowView", "write_row_png", "write_tree_png"]

MAX_POINTS = 40_000  # per side and panel: enough to read the row, small enough to draw in a second
DEPTH_WINDOW_M = 2.0  # m either side of the trunk line: the neighbouring rows are left out
SIDE_COLOURS = {"front": "#1f77b4", "back": "#ff7f0e"}


@dataclass(frozen=True)
class RowView:
    """One column of the figure: both sides' points and trunk bases in map (m)."""

    title: str
    points: dict[str, np.ndarray]  # side -> (P, 3)
    trunks: dict[str, np.ndarray]  # side -> (T, 3) trunk bases
    # per tree: its trunk's foot (3,) in map, its height (m, None: not measured) and its label ("id, height,
    # volume"), written above the tree in the front view
    labels: tuple[tuple[np.ndarray, float | None, str], ...] = ()


def write_row_png(path: Path, T_canon_map: np.ndarray, views: list[RowView], seed: int = 0) -> None:
    """Top view (X, Z) and front view (X, Y) of each RowView side by side; written atomically."""
    # The Figure API without pyplot: no global backend or figure registry (the side merger node draws in a
    # process that lives on), and pyplot's import alone was ~0.5 s of the merge stage's ~5 s
    from matplotlib.figure import Figure

    rng = np.random.default_rng(seed)
    R, t = T_canon_map[:3, :3], T_canon_map[:3, 3]

    def canon(p: np.ndarray) -> np.ndarray:
        return np.asarray(p, float).reshape(-1, 3) @ R.T + t

    trunk_z = [canon(v)[:, 2] for view in views for v in view.trunks.values() if len(v)]
    z0 = float(np.median(np.concatenate(trunk_z))) if trunk_z else 0.0
    fig = Figure(figsize=(7 * len(views), 7))
    axes = fig.subplots(2, len(views), squeeze=False, sharex=True)
    for col, view in enumerate(views):
        top, front = axes[0, col], axes[1, col]
        for side, pts in view.points.items():
            P = np.asarray(pts).reshape(-1, 3)  # (P, 3): millions; only the points drawn are carried over
            idx = np.flatnonzero(np.abs(P @ R[2] + t[2] - z0) <= DEPTH_WINDOW_M)
            if len(idx) > MAX_POINTS:
                idx = idx[rng.choice(len(idx), MAX_POINTS, replace=False)]
            c = canon(P[idx])
            kw = dict(s=0.3, c=SIDE_COLOURS.get(side, "grey"), alpha=0.35, linewidths=0, rasterized=True)
            top.scatter(c[:, 0], c[:, 2], label=f"{side} side", **kw)
            front.scatter(c[:, 0], c[:, 1], **kw)
        for side, bases in view.trunks.items():
            c = canon(bases)
            mk = dict(marker="x" if side == "front" else "+", s=40, c="k" if side == "front" else "r",
                      linewidths=1.2)
            top.scatter(c[:, 0], c[:, 2], label=f"{side} trunks", **mk)
            front.scatter(c[:, 0], c[:, 1], **mk)
        for foot, height, text in view.labels:
            f = canon(foot)[0]
            front.annotate(text, (f[0], f[1] + (height or 0.0)), xytext=(0, 4), textcoords="offset points",
                           ha="center", va="bottom", fontsize=6)
        top.set_title(f"{view.title}: top view")
        front.set_title(f"{view.title}: front view")
        top.set_ylabel("depth Z (m)")
        front.set_ylabel("up Y (m)")
        front.set_xlabel("along the row X (m)")
        for ax in (top, front):
            ax.set_aspect("equal", adjustable="datalim")
            ax.grid(True, linewidth=0.3)
        top.legend(loc="upper right", fontsize=7, markerscale=2)
    fig.tight_layout()
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.partial.png")
    fig.savefig(tmp, dpi=110)  # Agg, the default canvas of a bare Figure
    os.replace(tmp, path)


TREE_MAX_POINTS = 6_000  # per tree figure: the crown reads as well, and a figure draws in ~0.3 s
CLASS_COLOURS = {2: "#8c6d31", 5: "#2ca02c", 14: "#7f7f7f", 64: "#6b3d1e", 65: "#1f77b4", 66: "#d62728"}


def write_tree_png(path: Path, title: str, points_row: np.ndarray, classes: np.ndarray, height_m: float | None,
                   clear_m: float | None, seed: int = 0) -> None:
    """trees/<id>.png: one tree's segmented points in its row frame (x along the row, y across, z up, origin
    at its foot), from the front (x, z) and from the side (y, z), coloured by class, with its local ground
    (z = 0), its clear trunk and its height; written atomically."""
    from matplotlib.figure import Figure

    P = np.asarray(points_row, float).reshape(-1, 3)
    cls = np.asarray(classes)
    if len(P) > TREE_MAX_POINTS:
        keep = np.random.default_rng(seed).choice(len(P), TREE_MAX_POINTS, replace=False)
        P, cls = P[keep], cls[keep]
    colours = [CLASS_COLOURS.get(int(c), "k") for c in cls]
    fig = Figure(figsize=(8, 5))
    front, side = fig.subplots(1, 2, sharey=True)
    fig.subplots_adjust(left=0.09, right=0.98, bottom=0.1, top=0.86, wspace=0.08)
    for ax, (i, name) in ((front, (0, "along the row x (m)")), (side, (1, "across the row y (m)"))):
        ax.scatter(P[:, i], P[:, 2], s=0.5, c=colours, linewidths=0, rasterized=True)
        ax.axhline(0.0, color="#8c6d31", linewidth=1.0)  # the local ground
        for level, style in ((height_m, "-"), (clear_m, "--")):
            if level is not None:
                ax.axhline(level, color="k", linewidth=0.8, linestyle=style)
        ax.set_xlabel(name)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(True, linewidth=0.3)
    front.set_ylabel("up z (m): ground, clear trunk (dashed), height (solid)")
    front.set_title("from the front")
    side.set_title("from the side")
    fig.suptitle(title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.partial.png")
    fig.savefig(tmp, dpi=100)
    os.replace(tmp, path)
