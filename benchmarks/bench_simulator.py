"""Simulator throughput and bag read speed.

Simulator: the standard scenario at 640x480, 5 trees, front side: per frame the
time to render (ray cast + shading), apply the sensor model, write the bag
messages (camera info, colour, 16UC1 depth) and the ground-truth work
(visibility bookkeeping + instance mask PNG), as in `simulate`. Medians over
--frames frames after one warm-up frame (which builds the ray-casting scene).

Bag read: decode every frame of the written bag with `read_rgbd`; bag size in
MB (10^6 bytes) over seconds, median of --reads runs.

    python benchmarks/bench_simulator.py [--frames 20] [--reads 3] [--trees 5] [--seed 0]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np

from orchard_mapping.config import TopicsConfig
from orchard_mapping.io.bag_writer import BagWriter
from orchard_mapping.io.bags import describe_bag, read_rgbd
from orchard_mapping.sim.render import Renderer, SensorModel
from orchard_mapping.sim.scenario import load_scenario
from orchard_mapping.sim.scene import build_scene
from orchard_mapping.sim.simulate import instance_mask, intrinsics_of
from orchard_mapping.sim.trajectory import side_path
from orchard_mapping.sim.truth import VisibilityAccumulator


def bench_simulator(frames: int, trees: int, seed: int, bag_dir: Path) -> tuple[dict[str, float], dict[str, float]]:
    """Median seconds per frame for each part, and one-off setup seconds."""
    setup: dict[str, float] = {}
    t = time.perf_counter()
    sc = load_scenario("standard", {"row.n_trees": trees, "camera.width": 640, "camera.height": 480})
    scene = build_scene(sc, seed)
    setup["build_scene"] = time.perf_counter() - t
    intr = intrinsics_of(sc)
    renderer = Renderer(scene, intr, seed)
    sensor = SensorModel.from_camera(sc.camera)
    acc = VisibilityAccumulator(scene, intr, sc.trunk.diameter_height_m)
    path = side_path(sc, "front", scene.row_x, scene.terrain, np.random.default_rng([seed, 1]), 1_700_000_000.0)
    n = min(frames + 1, len(path.stamps))
    # Frames from the middle of the level sweep, where the trees fill the view.
    start = max(0, min(len(path.stamps) // 4, len(path.stamps) - n))
    rng = np.random.default_rng([seed, 2])
    topics = TopicsConfig()
    parts: dict[str, list[float]] = {"render": [], "sensor": [], "bag_write": [], "truth+mask": []}
    mask_dir = bag_dir.parent / "masks"
    mask_dir.mkdir(exist_ok=True)
    with BagWriter(bag_dir) as bag:
        for k in range(start, start + n):
            T, stamp = path.poses[k], float(path.stamps[k])
            t0 = time.perf_counter()
            out = renderer.render(T, stamp - float(path.stamps[0]))
            t1 = time.perf_counter()
            color, depth = sensor.apply(out, rng)
            t2 = time.perf_counter()
            bag.write_camera_info(topics.camera_info, stamp, intr)
            bag.write_color(topics.color, stamp, color, encoding="rgb8", frame_id=intr.frame_id)
            bag.write_depth(topics.depth, stamp, depth, encoding="16UC1", frame_id=intr.frame_id)
            t3 = time.perf_counter()
            acc.add(out, T)
            cv2.imwrite(str(mask_dir / f"{k:06d}.png"), instance_mask(out))
            t4 = time.perf_counter()
            if k == start:
                setup["first frame (raycast scene)"] = t4 - t0
                continue
            for name, dt in zip(parts, (t1 - t0, t2 - t1, t3 - t2, t4 - t3), strict=True):
                parts[name].append(dt)
    med = {name: statistics.median(v) for name, v in parts.items()}
    med["frames"] = len(parts["render"])
    return med, setup


def bench_bag_read(bag_dir: Path, reads: int) -> tuple[float, float, int]:
    """(bag MB, median seconds to decode every frame, frame count)."""
    size_mb = describe_bag(bag_dir).size_bytes / 1e6
    times = []
    count = 0
    for _ in range(reads):
        t = time.perf_counter()
        count = 0
        for frame in read_rgbd(bag_dir):
            count += int(frame.depth is not None)
        times.append(time.perf_counter() - t)
    return size_mb, statistics.median(times), count


def _print_table(title: str, header: tuple[str, ...], rows: list[tuple[str, ...]]) -> None:
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:
        print(f"\n{title}")
        widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
        for r in [header, *rows]:
            print("  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)))
        return
    table = Table(title=title)
    for i, h in enumerate(header):
        table.add_column(h, justify="left" if i == 0 else "right")
    for r in rows:
        table.add_row(*r)
    Console().print(table)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=20, help="frames to time (after one warm-up frame)")
    ap.add_argument("--reads", type=int, default=3, help="bag read runs (median)")
    ap.add_argument("--trees", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.frames < 1 or args.reads < 1:
        ap.error("--frames and --reads must be >= 1")

    with tempfile.TemporaryDirectory(prefix="bench_sim_") as tmp:
        bag_dir = Path(tmp) / "front"
        med, setup = bench_simulator(args.frames, args.trees, args.seed, bag_dir)
        size_mb, read_s, n_read = bench_bag_read(bag_dir, args.reads)

    total = sum(v for k, v in med.items() if k != "frames")
    rows = [(name, f"{1e3 * med[name]:.1f}", f"{100 * med[name] / total:.0f} %", f"{1 / med[name]:.1f}")
            for name in ("render", "sensor", "bag_write", "truth+mask")]
    rows.append(("total", f"{1e3 * total:.1f}", "100 %", f"{1 / total:.2f}"))
    _print_table(f"Simulator, standard scenario, 640x480, {args.trees} trees "
                 f"(median of {med['frames']} frames)", ("part", "ms / frame", "share", "frames / s"), rows)
    _print_table("One-off setup", ("step", "s"), [(k, f"{v:.2f}") for k, v in setup.items()])
    _print_table(f"Bag read (read_rgbd, all frames decoded, median of {args.reads} runs)",
                 ("bag", "MB", "frames", "s", "MB / s", "frames / s"),
                 [("front", f"{size_mb:.1f}", str(n_read), f"{read_s:.3f}", f"{size_mb / read_s:.1f}",
                   f"{n_read / read_s:.1f}")])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
