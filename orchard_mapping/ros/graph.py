"""The node graph `orchard-map launch` starts (see supervisor.py for how it is started and watched).

Nodes so far: `rgbd_odometry` (the camera topics in; each side's odometry, keyframes, fused cloud, trunk
cylinders and local grounds out), `trunk_detector` (answers the odometry node's detection requests),
`player` (replaying bags instead of a live camera) and `recorder`
(the graph's outputs to an MCAP bag). Every node reads the same parameters file (config/ros_params.yaml by
default: the keys of config/default.yaml).
"""

from __future__ import annotations

from pathlib import Path

from orchard_mapping.resources import config_dir
from orchard_mapping.ros.supervisor import NodeSpec

__all__ = ["graph_specs"]


def graph_specs(bags: list[Path], *, rate: float = 1.0, start_s: float = 0.0, loop: bool = False,
                record: Path | None = None, params: Path | None = None, restart: bool = True,
                side: str | None = None, sides: list[str] | None = None) -> list[NodeSpec]:
    """The nodes of the graph, in start order. With bags, the player replays them (front, then back, unless
    `sides` says otherwise) and the odometry node exits once it has published their side maps, which ends
    the graph; without, the graph runs on the live camera topics until stopped."""
    ros_args = ("--ros-args", "--params-file", str(params or config_dir() / "ros_params.yaml"))
    odometry = [*ros_args, "-p", "detector:=node"]
    if side:
        odometry += ["-p", f"side:={side}"]
    specs = []
    if record is not None:
        specs.append(NodeSpec("recorder", "recorder", (str(record),)))
    # a dead detector is started again also on bags: the odometry node flags what it could not see meanwhile
    specs.append(NodeSpec("trunk_detector", "trunk_detector", ros_args, restart=restart))
    if bags:
        sides = sides or (["front", "back"][: len(bags)] if len(bags) <= 2 else None)
        odometry += ["-p", f"exit_after_sides:={len(bags) if not loop else 0}"]
        specs.append(NodeSpec("rgbd_odometry", "rgbd_odometry", tuple(odometry), ends_graph=not loop))
        player = [str(b) for b in bags] + ["--rate", str(rate), "--start", str(start_s)]
        player += [a for s in (sides or []) for a in ("--side", s)]
        if loop:
            player.append("--loop")
        specs.append(NodeSpec("player", "player", tuple(player), finite=True))
    else:
        specs.append(NodeSpec("rgbd_odometry", "rgbd_odometry", tuple(odometry), restart=restart))
    return specs
