"""`trait_reporter`: the trees of the merged row out, as messages, RViz/Foxglove markers and report files.

In:  /orchard/merged/trees  TreeTraitsArray from the side merger (latched): each tree's position in map,
     its two-side trunk diameter and each side's own, flags
Out (latched, frame map):
     /orchard/trees          orchard_mapping_msgs/TreeTraitsArray: every tree with the traits measured so far
                             (trunk diameter, height, canopy volume, fruit counts with the fruit
                             stage; -1 where not measured, as in trees.json where it is null)
     /orchard/tree_markers   visualization_msgs/MarkerArray: a cylinder per trunk (its diameter, 0.6 m
                             high, green when seen from both sides, orange from one), a text label
                             (tree id, diameter in mm, height, canopy volume, fruit) above it and, where the
                             height is measured, a translucent box for the crown (namespace `crowns`)
With `out_dir` set, trees.json and trees.csv are written there as `orchard-map run` writes them (each
file atomically; the trees are validated before anything is written). With `exit_after_reports`
(replaying bags) the node exits 0 after that many reports, which ends the graph.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from orchard_mapping_msgs.msg import TreeTraitsArray
from rclpy.node import Node
from visualization_msgs.msg import Marker, MarkerArray

from orchard_mapping.errors import ResultFormatError
from orchard_mapping.io.results import ResultTree, write_trees
from orchard_mapping.ros.graph import MERGED_TREES_TOPIC
from orchard_mapping.ros.messages import stamp_header, trees_from_msg, trees_to_msg
from orchard_mapping.ros.params import ConfigParameters
from orchard_mapping.ros.qos import LATCHED
from orchard_mapping.ros.spin import StopNode, run_node

__all__ = ["TREES_TOPIC", "TraitReporterNode", "main", "tree_markers"]

TREES_TOPIC = "/orchard/trees"
MARKERS_TOPIC = "/orchard/tree_markers"
_MARKER_HEIGHT_M = 0.6  # m, drawn trunk length: the part a diameter is read on and a little above
_DEFAULT_DIAMETER_M = 0.1  # m, drawn for a trunk whose diameter was not measured


def tree_markers(trees: list[ResultTree], frame_id: str, stamp: float) -> MarkerArray:
    """A trunk cylinder and a text label per tree (RViz / Foxglove), ids 2k and 2k+1; the first marker
    deletes what an earlier report drew."""
    out = MarkerArray()
    clear = Marker()
    clear.action = Marker.DELETEALL
    out.markers.append(clear)
    for t in trees:
        both = not any(f.startswith("seen_from_") for f in t.flags)
        d = t.trunk_diameter_m if t.trunk_diameter_m is not None else _DEFAULT_DIAMETER_M
        trunk, label = Marker(), Marker()
        for k, m in enumerate((trunk, label)):
            stamp_header(m.header, stamp, frame_id)
            m.ns, m.id, m.action = "trees", 2 * t.id + k, Marker.ADD
            m.pose.orientation.w = 1.0
            m.color.a = 1.0
        trunk.type = Marker.CYLINDER
        trunk.pose.position.x, trunk.pose.position.y, trunk.pose.position.z = t.position
        # map is odom_front, the camera's optical frame: y points down, so "up the trunk" is -y. The marker's
        # axis is its z: turned onto -y (a quarter turn about x).
        trunk.pose.position.y -= _MARKER_HEIGHT_M / 2
        trunk.pose.orientation.x = trunk.pose.orientation.w = math.sqrt(0.5)
        trunk.scale.x = trunk.scale.y = float(d)
        trunk.scale.z = _MARKER_HEIGHT_M
        trunk.color.r, trunk.color.g, trunk.color.b = (0.2, 0.8, 0.2) if both else (1.0, 0.6, 0.1)
        label.type = Marker.TEXT_VIEW_FACING
        label.pose.position.x, label.pose.position.y, label.pose.position.z = t.position
        label.pose.position.y -= _MARKER_HEIGHT_M + 0.15
        label.scale.z = 0.12  # m, text height
        label.color.r = label.color.g = label.color.b = 1.0
        label.text = f"tree {t.id}" + (f": {1000 * t.trunk_diameter_m:.0f} mm" if t.trunk_diameter_m else "")
        out.markers += [trunk, label]
        if t.height_m is not None:
            label.text += f", {t.height_m:.2f} m" + (f", {t.canopy_volume_m3:.2f} m3" if t.canopy_volume_m3 else "")
            label.pose.position.y = t.position[1] - t.height_m - 0.15  # above the crown
            out.markers.append(_crown_box(t, frame_id, stamp))
        if t.fruit_count is not None:
            label.text += f", {t.fruit_count} fruit"
    return out


def _crown_box(t: ResultTree, frame_id: str, stamp: float) -> Marker:
    """The crown as a box from the clear trunk to the top, its footprint square with the canopy volume's area
    (the crown's shape is in trees.laz). Up is map's -y (the front camera's optical frame)."""
    box = Marker()
    stamp_header(box.header, stamp, frame_id)
    box.ns, box.id, box.action, box.type = "crowns", t.id, Marker.ADD, Marker.CUBE
    base = float(t.extra.get("clear_trunk_height_m", 0.0) or 0.0)
    tall = max(float(t.height_m) - base, 0.05)
    side = math.sqrt(t.canopy_volume_m3 / tall) if t.canopy_volume_m3 else 0.5
    box.pose.position.x, box.pose.position.y, box.pose.position.z = t.position
    box.pose.position.y -= base + tall / 2
    box.pose.orientation.w = 1.0
    box.scale.x, box.scale.y, box.scale.z = side, tall, side
    box.color.r, box.color.g, box.color.b, box.color.a = 0.3, 0.7, 0.3, 0.35
    return box


class TraitReporterNode(Node):
    def __init__(self) -> None:
        super().__init__("trait_reporter")
        self.params = ConfigParameters(self)
        self.declare_parameter("out_dir", "")  # where trees.json and trees.csv go ("": not written)
        self.declare_parameter("exit_after_reports", 0)  # replaying bags: exit after this many (0: run on)
        self.reports = 0
        self._stop: int | None = None
        self._trees = self.create_publisher(TreeTraitsArray, TREES_TOPIC, LATCHED)
        self._markers = self.create_publisher(MarkerArray, MARKERS_TOPIC, LATCHED)
        self.create_subscription(TreeTraitsArray, MERGED_TREES_TOPIC, self._on_trees, LATCHED)
        self.create_timer(0.2, self._check_done)

    def _check_done(self) -> None:
        # the node exits once every subscriber (the recorder, RViz) acknowledged the last report (ros/spin.py)
        if self._stop is not None:
            raise StopNode(self._stop)

    def _on_trees(self, msg: TreeTraitsArray) -> None:
        frame, stamp, trees = trees_from_msg(msg)
        out = self.get_parameter("out_dir").value
        if out:
            try:
                Path(out).mkdir(parents=True, exist_ok=True)
                write_trees(out, trees, frame=frame)
            except (ResultFormatError, OSError) as err:
                self.get_logger().error(f"trees of {MERGED_TREES_TOPIC} not written to {out}: {err}")
                self._stop = 1
                return
        self._trees.publish(trees_to_msg(trees, frame, stamp))
        self._markers.publish(tree_markers(trees, frame, stamp))
        self.reports += 1
        both = sum(1 for t in trees if not any(f.startswith("seen_from_") for f in t.flags))
        self.get_logger().info(f"report {self.reports}: {len(trees)} trees ({both} seen from both sides)"
                               + (f", written to {out}" if out else ""))
        wanted = self.get_parameter("exit_after_reports").value
        if wanted and self.reports >= wanted:
            self._stop = 0


def main(argv: list[str] | None = None) -> int:
    return run_node(TraitReporterNode, "trait_reporter")


if __name__ == "__main__":
    sys.exit(main())
