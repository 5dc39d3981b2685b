"""The node graph `orchard-map launch` starts (see supervisor.py for how it is started and watched).

Nodes: `rgbd_odometry` (the camera topics in; each side's odometry, keyframes, fused cloud, trunk
cylinders and whole side map out), `trunk_detector` (answers the odometry node's detection
requests), `local_ground_fitter` (each fused side's trunk landmarks, coarse axes and local grounds, which the
odometry node fits the trunk cylinders against), `side_merger` (both side maps in; the merge, the merged cloud, trunks, grounds and trees out),
`trait_reporter` (the trees as TreeTraitsArray, RViz markers and trees.json / trees.csv), `player`
(replaying bags instead of a live camera) and `recorder` (the graph's outputs to an MCAP bag). Every node reads the same parameters file (config/ros_params.yaml by
default: the keys of config/default.yaml).
"""

from __future__ import annotations

from pathlib import Path

from orchard_mapping.errors import OrchardMappingError
from orchard_mapping.resources import config_dir
from orchard_mapping.ros.supervisor import NodeSpec


class GraphError(OrchardMappingError, ValueError):
    """A graph that cannot be started as asked (names what is wrong)."""


# topic names only (the node modules import rclpy and the core: the launcher does not need them)
MERGED_TREES_TOPIC = "/orchard/merged/trees"


def side_map_topic(side: str) -> str:
    return f"/orchard/{side}/side_map"

__all__ = ["graph_specs"]


def graph_specs(bags: list[Path], *, rate: float = 1.0, start_s: float = 0.0, loop: bool = False,
                record: Path | None = None, params: Path | None = None, restart: bool = True,
                side: str | None = None, sides: list[str] | None = None, out: Path | None = None,
                drive: bool = False) -> list[NodeSpec]:
    """The nodes of the graph, in start order. With bags, the player replays them (front, then back, unless
    `sides` says otherwise) and the odometry node exits once it has published their side maps; with both
    sides the trait reporter's first report then ends the graph (a refused merge ends it with a failure),
    with one side the odometry node's exit does. Without bags the graph runs on the live camera topics
    until stopped. `out`: the merge's and the trees' files are written there. `drive`: one bag holds a whole
    drive round the row (front, U-turn, back): its sides come from its side topic or the U-turn
    (input.side_source), and both are merged."""
    ros_args = ("--ros-args", "--params-file", str(params or config_dir() / "ros_params.yaml"))
    out_arg = ("-p", f"out_dir:={Path(out).resolve()}") if out is not None else ()
    odometry = [*ros_args, "-p", "detector:=node", "-p", "ground_fitter:=node"]
    if side:
        odometry += ["-p", f"side:={side}"]
    specs = []
    # Every node is started again when it dies, on bags too (docs/ros.md, "When a node dies"); what it had
    # received comes back to it: the latched results of the others, and on a replay the whole recording (the
    # player starts again with the odometry node). The recorder is stopped last (it takes what the others sent)
    # and a restarted one carries on the bag its predecessor was writing.
    if record is not None:
        specs.append(NodeSpec("recorder", "recorder", (str(record), "--prefix", "/orchard", "--prefix", "/tf",
                                                       "--prefix", "/tf_static"), restart=restart, stop_last=True))
    # the request waiting for an answer is latched: a restarted detector answers it, nothing is flagged
    specs.append(NodeSpec("trunk_detector", "trunk_detector", ros_args, restart=restart))
    # restarted, the ground fitter gets the latched side geometry again and answers it (if it never does, the
    # odometry node fits the same grounds itself after ground_fitter_timeout_s: the same grounds)
    specs.append(NodeSpec("local_ground_fitter", "local_ground_fitter", ros_args, restart=restart))
    if bags:
        if drive and len(bags) != 1:
            raise GraphError(f"--drive replays one bag holding both sides, got {len(bags)} bags")
        if not drive:
            sides = sides or (["front", "back"][: len(bags)] if len(bags) <= 2 else None)
        two = drive or sides is None or {"front", "back"} <= set(sides)  # a merge to wait for
        odometry += ["-p", f"exit_after_sides:={(2 if drive else len(bags)) if not loop else 0}",
                     "-p", "replayed_camera:=true"]
        if two:
            # restarted, they receive the latched side maps (the merger) and trees (the reporter) again
            # (a refused merge, exit code 2, and trees that cannot be written, 1, end the graph: no restart)
            specs.append(NodeSpec("side_merger", "side_merger", (*ros_args, *out_arg, "-p", "exit_on_refusal:=true"),
                                  restart=restart, final_codes=(2,)))
            specs.append(NodeSpec("trait_reporter", "trait_reporter",
                                  (*ros_args, *out_arg, "-p", f"exit_after_reports:={0 if loop else 1}"),
                                  ends_graph=not loop, restart=restart, final_codes=(1, 2)))
        # restarted, the odometry node gets the recording again from its start (the player starts again with it):
        # the same side maps, only later
        specs.append(NodeSpec("rgbd_odometry", "rgbd_odometry", tuple(odometry), ends_graph=not loop and not two,
                              finite=two, restart=restart, restart_with=("player",), final_codes=(1, 2)))
        # the odometry node's own readers, not the recorder's, must have matched before the first frame, and the
        # nodes it asks or feeds must be up (a node still importing the core takes the cores from the first
        # frames). A side change is published once the odometry node acknowledged the images before it
        # (--side-acks). --wait is only a guard: a graph not up by then is not played to (the player fails).
        player = [str(b) for b in bags] + ["--rate", str(rate), "--start", str(start_s), "--wait", "600",
                                           "--side-acks",
                                           "--wait-reader", "rgbd_odometry", "--wait-node", "trunk_detector",
                                           "--wait-node", "local_ground_fitter"]
        if two:  # the side merger and the trait reporter have started (imported the core) before the first frame
            player += ["--wait-node", "side_merger", "--wait-node", "trait_reporter"]
        player += [a for s in (sides or []) for a in ("--side", s)]
        if loop:
            player.append("--loop")
        specs.append(NodeSpec("player", "player", tuple(player), finite=True))
    else:
        specs.append(NodeSpec("side_merger", "side_merger", (*ros_args, *out_arg), restart=restart))
        specs.append(NodeSpec("trait_reporter", "trait_reporter", (*ros_args, *out_arg), restart=restart))
        specs.append(NodeSpec("rgbd_odometry", "rgbd_odometry", tuple(odometry), restart=restart))
    return specs
