"""`orchard-map inspect`: what a recording holds, read back through the same bag reader the pipeline uses."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from orchard_mapping.config import TopicsConfig
from orchard_mapping.errors import BagReadError
from orchard_mapping.io.bags import describe_bag, read_rgbd


def _is_bag(path: Path) -> bool:
    return path.suffix == ".mcap" or (path / "metadata.yaml").is_file()


def bag_table(path: Path) -> tuple[Table, Table]:
    """Topic table and frame statistics of one bag (all frames decoded)."""
    summary = describe_bag(path)
    topics = Table(title=f"{path} ({summary.storage_id}, {summary.size_bytes / 1e6:.1f} MB, "
                         f"{summary.duration_s:.1f} s)")
    topics.add_column("topic")
    topics.add_column("type")
    topics.add_column("messages", justify="right")
    for name, msgtype, count in summary.topics:
        topics.add_row(name, msgtype, str(count))

    seq = read_rgbd(path, TopicsConfig())
    valid, med, p95 = [], [], []
    for frame in seq:
        d = frame.depth
        ok = d > 0
        valid.append(ok.mean())
        if ok.any():
            med.append(float(np.median(d[ok])))
            p95.append(float(np.percentile(d[ok], 95)))
    k = seq.intrinsics
    stats = Table(title="RGB-D frames read back", show_header=False)
    stats.add_row("frames (colour paired with depth)", f"{len(seq)} ({seq.dropped} unpaired dropped)")
    stats.add_row("rate", f"{(len(seq) - 1) / seq.duration:.1f} Hz" if seq.duration > 0 else "-")
    stats.add_row("image", f"{k.width}x{k.height}, fx {k.fx:.1f} fy {k.fy:.1f} cx {k.cx:.1f} cy {k.cy:.1f}")
    stats.add_row("valid depth pixels", f"{100 * np.mean(valid):.1f} % (min {100 * np.min(valid):.1f} %)")
    if med:
        stats.add_row("depth median / 95th pct", f"{np.median(med):.2f} m / {np.median(p95):.2f} m")
    labels = sorted({s for s in seq.sides if s})
    if labels:
        stats.add_row("side labels", ", ".join(f"{s}: {seq.sides.count(s)}" for s in labels))
    return topics, stats


def truth_table(truth: dict) -> Table:
    t = Table(title=f"Ground truth per tree (scenario {truth['scenario']}, seed {truth['seed']}; diameter at "
                    f"{truth['diameter_height_m']:.2f} m, canopy alpha {truth['canopy_alpha_m']} m)")
    t.caption = "fruit seen: F front, B back, F|B either, F&B both; trunk/top seen: in view from front/back"
    for col in ("tree", "x m", "diam mm", "height m", "canopy m3", "fruit", "F", "B", "F|B", "F&B",
                "trunk F/B", "top F/B"):
        t.add_column(col, justify="right")
    for tree in truth["trees"]:
        fv = tree["fruit_visible"]
        ob = tree["observed"]
        yn = {True: "y", False: "n"}
        t.add_row(
            str(tree["id"]), f"{tree['position'][0]:.2f}", f"{1000 * tree['trunk']['diameter_m']:.1f}",
            f"{tree['height_m']:.2f}", f"{tree['canopy_volume_m3']:.2f}", str(tree["fruit_count"]),
            str(fv["front"]), str(fv["back"]), str(fv["either"]), str(fv["both"]),
            f"{yn[ob['front']['trunk_at_diameter_height']]}/{yn[ob['back']['trunk_at_diameter_height']]}",
            f"{yn[ob['front']['top']]}/{yn[ob['back']['top']]}",
        )
    return t


def sides_table(truth: dict, title: str = "") -> Table:
    t = Table(title=f"{title}Recordings (ground truth)")
    for col in ("side", "bag", "frame", "poses", "path m", "duration s"):
        t.add_column(col)
    for side, s in truth["sides"].items():
        t.add_row(side, s["bag"], s["frame"], str(len(s["trajectory"])), f"{s['path_length_m']:.1f}",
                  f"{s['duration_s']:.1f}")
    T = np.array(truth["T_front_back"])
    angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
    t.caption = f"true side merge T_front_back: rotation {angle:.1f} deg, translation {np.linalg.norm(T[:3, 3]):.2f} m"
    return t


def inspect_path(path: Path, console: Console) -> None:
    if not path.exists():
        raise BagReadError("path does not exist", bag=str(path))
    if _is_bag(path):
        for table in bag_table(path):
            console.print(table)
        return
    bags = [p for p in sorted(path.iterdir()) if p.is_dir() and _is_bag(p)]
    truth_path = path / "ground_truth.json"
    if not bags and not truth_path.is_file():
        raise BagReadError("neither a bag nor a simulation folder (no metadata.yaml, no ground_truth.json)",
                           bag=str(path))
    for bag in bags:
        for table in bag_table(bag):
            console.print(table)
    if truth_path.is_file():
        truth = json.loads(truth_path.read_text())
        if "rows" in truth and "drive" in truth:  # a simulated block (sim.block): each row's truth beside it
            console.print(block_table(truth))
            for row in truth["rows"]:
                row_truth = json.loads((path / row["truth"]).read_text())
                console.print(sides_table(row_truth, f"row {row['row']}: "))
                console.print(truth_table(row_truth))
            return
        console.print(sides_table(truth))
        console.print(truth_table(truth))


def block_table(truth: dict) -> Table:
    t = Table(title=f"Block (scenario {truth['scenario']}, seed {truth['seed']}): one drive, "
                    f"{truth['drive']['frames']} frames in bag {truth['drive']['bag']}")
    for col in ("row", "y m", "trees", "front frames", "back frames"):
        t.add_column(col, justify="right")
    for row in truth["rows"]:
        t.add_row(str(row["row"]), f"{row['y_m']:.2f}", ", ".join(map(str, row["tree_ids"])),
                  str(row["passes"]["front"]["frames"]), str(row["passes"]["back"]["frames"]))
    return t
