"""`side_merger`: both sides' maps in, the merged row out (paper: "Merging Two-Sides 3D Reconstruction").

It runs the same core as `orchard-map run` (pipeline.merge_and_measure: initial alignment, initial
transform, semantic bundle adjustment, two-side trunk diameters, then each tree's height and canopy volume)
once it holds a map of each side, and again whenever a side's map is replaced.

In:  `/orchard/<side>/side_map`  orchard_mapping_msgs/SideMap from the odometry node (latched)
Out (latched, frame `map` = odom_front):
     /orchard/side_merge               orchard_mapping_msgs/SideMerge
     /orchard/merged/cloud             sensor_msgs/PointCloud2, both sides' clouds carried into map
     /orchard/merged/trunk_cylinders   TrunkCylinderArray: each side's trunks carried into map by the
                                       semantic BA's keyframe poses (tree_id: the tree they belong to)
     /orchard/merged/local_grounds     LocalGroundArray: each side's local grounds, likewise
     /orchard/merged/trees             TreeTraitsArray: the trees of the merge (position, two-side and
                                       per-side trunk diameters, height, canopy volume, flags) for the
                                       trait reporter
     /orchard/side_merger/status       std_msgs/String JSON: merges made, refusals and why, seconds
     /tf_static                        map -> odom_front (identity) and map -> odom_back (the merge's rigid
                                       transform), so RViz shows each side's odom frames in map
With `out_dir` set, the merge's files (side_merge.json, both trajectories in map, merged.ply, row.png,
trees.laz, trees/<id>.png) are written there as `orchard-map run` writes them, each file atomically. A refused merge (too few trees
seen from both sides, or pairs that disagree) is published in the status and logged; nothing is guessed.
With `exit_on_refusal` (replaying bags) a refusal also ends the node with exit code 2, which stops the
graph as `orchard-map run` stops with 2; otherwise the node waits for the next map of either side.
"""

from __future__ import annotations

import json
import sys
import threading
import time
import traceback
from pathlib import Path

import numpy as np
from orchard_mapping_msgs.msg import (
    LocalGroundArray,
    SideMap as SideMapMsg,
    SideMerge,
    TreeTraitsArray,
    TrunkCylinderArray,
)
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String

from orchard_mapping.core.geometry import matrix_to_quat
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.errors import AlignmentError, OrchardMappingError
from orchard_mapping.io.results import staged_folder
from orchard_mapping.io.sidemap_codec import SIDE_MAP_ENCODING, SideMapFormatError, decode_side_map
from orchard_mapping.pipeline import (
    MergeOutcome,
    RowLabels,
    map_poses,
    merge_and_measure,
    ray_in_map,
    tree_of_trunk,
    write_merge,
    write_tree_cloud,
)
from orchard_mapping.ros.clouds import cloud_to_msg
from orchard_mapping.ros.graph import MERGED_TREES_TOPIC, side_map_topic
from orchard_mapping.ros.messages import (
    TrunkRecord,
    ground_records,
    grounds_to_msg,
    stamp_header,
    trees_to_msg,
    trunks_to_msg,
)
from orchard_mapping.ros.params import ConfigParameters
from orchard_mapping.ros.qos import LATCHED
from orchard_mapping.ros.spin import StopNode, run_node
from orchard_mapping.ros.tf import StaticTransforms, transform_msg

__all__ = ["MERGED_TREES_TOPIC", "SideMergerNode", "main", "side_map_topic"]

MAP_FRAME = "map"


class SideMergerNode(Node):
    def __init__(self) -> None:
        super().__init__("side_merger")
        self.params = ConfigParameters(self)
        self.declare_parameter("out_dir", "")  # where the merge's files go ("": not written)
        self.declare_parameter("exit_on_refusal", False)  # replaying bags: a refused merge ends the node (2)
        self.maps: dict[str, SideMap] = {}
        self.merges = 0
        self.refused: list[str] = []
        self.errors: list[str] = []
        self.seconds: list[float] = []
        self._stop: int | None = None
        self._writer: threading.Thread | None = None  # writing the last merge's files (out_dir)
        self._pubs = {
            "merge": self.create_publisher(SideMerge, "/orchard/side_merge", LATCHED),
            "cloud": self.create_publisher(PointCloud2, "/orchard/merged/cloud", LATCHED),
            "trunks": self.create_publisher(TrunkCylinderArray, "/orchard/merged/trunk_cylinders", LATCHED),
            "grounds": self.create_publisher(LocalGroundArray, "/orchard/merged/local_grounds", LATCHED),
            "trees": self.create_publisher(TreeTraitsArray, MERGED_TREES_TOPIC, LATCHED),
            "status": self.create_publisher(String, "/orchard/side_merger/status", LATCHED),
        }
        self._static_tf = StaticTransforms(self)
        for side in ("front", "back"):
            self.create_subscription(SideMapMsg, side_map_topic(side), lambda m, s=side: self._on_map(s, m), LATCHED)
        self.create_timer(0.2, self._check_done)
        self._publish_status()

    def _check_done(self) -> None:
        if self._stop is not None:
            raise StopNode(self._stop)

    def _publish_status(self) -> None:
        self._pubs["status"].publish(String(data=json.dumps({
            "sides": sorted(self.maps), "merges": self.merges, "refused": self.refused, "errors": self.errors,
            "seconds": [round(s, 3) for s in self.seconds]})))

    def _on_map(self, side: str, msg: SideMapMsg) -> None:
        where = f"{side_map_topic(side)} (stamp {msg.header.stamp.sec}.{msg.header.stamp.nanosec:09d})"
        try:
            if msg.encoding != SIDE_MAP_ENCODING:
                raise SideMapFormatError(f"{where}: encoding {msg.encoding!r}, this node reads {SIDE_MAP_ENCODING!r}")
            sm = decode_side_map(msg.data.tobytes() if hasattr(msg.data, "tobytes") else bytes(msg.data), where)
            if sm.side != side:
                raise SideMapFormatError(f"{where}: holds the {sm.side!r} side's map")
        except SideMapFormatError as err:
            self.get_logger().error(str(err))
            self.errors.append(str(err))
            self._publish_status()
            return
        self.maps[side] = sm
        self.get_logger().info(f"{side} side map: {len(sm.keyframe_poses)} keyframes, {len(sm.trunks)} trunks")
        if set(self.maps) == {"front", "back"}:
            self._merge()
        self._publish_status()

    def _merge(self) -> None:
        cfg = self.params.config
        t0 = time.perf_counter()
        try:
            merged, clouds, trees, labels, _ = merge_and_measure(self.maps, cfg)
        except AlignmentError as err:
            self.get_logger().error(f"the two sides were not merged: {err}")
            self.refused.append(str(err))
            if self.get_parameter("exit_on_refusal").value:
                self._stop = 2
            return
        self.seconds.append(time.perf_counter() - t0)
        self.merges += 1
        self._publish(merged, clouds, trees)
        steps = ", ".join(f"{k} {v:.2f} s" for k, v in merged.seconds.items())  # not in side_merge.json
        self.get_logger().info(f"merged ({merged.method}) on {len(merged.pairs)} trunk pairs in "
                               f"{self.seconds[-1]:.2f} s ({steps}): {len(trees)} trees")
        out = self.get_parameter("out_dir").value
        if out:
            # The files after the messages: drawing and writing them (row.png, a picture per tree, trees.laz) took
            # 7.5 s of the 17 s between the second side map and the trees on the 10-tree row. A later merge's
            # files wait for these; the node's exit waits for the last (close).
            if self._writer is not None:
                self._writer.join()
            maps = dict(self.maps)
            self._writer = threading.Thread(target=self._write, args=(Path(out), merged, maps, clouds, labels, trees),
                                            name="merge-files")
            self._writer.start()

    def close(self) -> None:
        """Wait for the merge's files to be written (a stop meanwhile leaves the earlier set whole)."""
        if self._writer is not None:
            self._writer.join()

    def _write(self, out: Path, merged: MergeOutcome, maps: dict[str, SideMap], clouds: dict[str, np.ndarray],
               labels: RowLabels, trees: list) -> None:
        """The merge's files into `out`, each moved in only once all were written (a stop meanwhile leaves
        the earlier set whole), as `orchard-map run` writes its result folder. Runs on the writer thread."""
        try:
            with staged_folder(out) as stage:
                write_merge(stage, merged, maps, clouds, trees)
                write_tree_cloud(stage, labels, trees)
        except Exception as err:  # noqa: BLE001 - a full or unwritable folder: reported, and the node ends with 2
            text = f"the merge's files were not written to {out}: {err}"
            self.get_logger().error(text if isinstance(err, OrchardMappingError) else
                                    f"{text}\n{traceback.format_exc()}")
            self.errors.append(text)
            self._publish_status()
            self._stop = 2

    def _publish(self, merged: MergeOutcome, clouds: dict[str, np.ndarray], trees: list) -> None:
        front, back = self.maps["front"], self.maps["back"]
        stamp = float(max(front.keyframe_stamps[-1], back.keyframe_stamps[-1]))
        m = SideMerge()
        stamp_header(m.header, stamp, MAP_FRAME)
        m.child_frame_id = back.frame_id
        T = merged.T_front_back
        s = float(np.cbrt(np.linalg.det(T[:3, :3])))
        m.scale = s
        q = matrix_to_quat(T[:3, :3] / s)
        m.transform.translation.x, m.transform.translation.y, m.transform.translation.z = (float(v) for v in T[:3, 3])
        m.transform.rotation.x, m.transform.rotation.y, m.transform.rotation.z, m.transform.rotation.w = (
            float(v) for v in q)
        al = merged.alignment
        m.boundary_rmse = float(al.boundary_rms_m) if al is not None else float("nan")
        gaps = list(merged.sba.gaps_after_mm.values()) if merged.sba is not None else []
        m.trunk_rmse = float(np.sqrt(np.mean(np.square(gaps))) / 1000.0) if gaps else float("nan")
        m.ground_rmse = float("nan")  # not measured per pair yet
        m.matched_trunks = len(merged.pairs)
        n = max(len(front.trunks), len(back.trunks))
        m.overlap = len(merged.pairs) / n if n else 0.0  # trees seen from both sides / from the side seeing more
        self._pubs["merge"].publish(m)
        # map is the front side's odom frame; the back side's odom frame by the rigid part of the merge (a
        # colour-only merge's scale is in SideMerge.scale: TF has none)
        R = np.eye(4)
        R[:3, :3], R[:3, 3] = T[:3, :3] / s, T[:3, 3]
        self._static_tf.send(transform_msg(np.eye(4), MAP_FRAME, front.frame_id, stamp),
                             transform_msg(R, MAP_FRAME, back.frame_id, stamp))
        self._pubs["cloud"].publish(cloud_to_msg(np.concatenate([clouds["front"], clouds["back"]]),
                                                 np.concatenate([front.cloud_colors, back.cloud_colors]),
                                                 MAP_FRAME, stamp))
        tree_of = tree_of_trunk(trees)
        poses = map_poses(merged, self.maps)
        trunks, grounds = [], []
        for side, sm in self.maps.items():
            for lm in sm.trunks:
                rec = TrunkRecord.from_landmark(lm, side)
                base, axis = ray_in_map(lm.base, lm.axis, sm, poses[side])
                trunks.append(TrunkRecord(tree_of.get((side, lm.id), -1), side, tuple(base), tuple(axis), rec.radius,
                                          rec.length, rec.radius_stddev, rec.fit_rmse, rec.inlier_count, rec.flags))
            for g in ground_records(sm.trunks, side):
                p, nrm = ray_in_map(np.asarray(g.point), np.asarray(g.normal), sm, poses[side])
                grounds.append(type(g)(tree_of.get((side, g.tree_id), -1), side, tuple(p), tuple(nrm),
                                       -float(nrm @ p), g.fit_rmse, g.inlier_count))
        self._pubs["trunks"].publish(trunks_to_msg(trunks, MAP_FRAME, stamp))
        self._pubs["grounds"].publish(grounds_to_msg(grounds, MAP_FRAME, stamp))
        self._pubs["trees"].publish(trees_to_msg(trees, MAP_FRAME, stamp))


def main(argv: list[str] | None = None) -> int:
    return run_node(SideMergerNode, "side_merger", finish=lambda node: node.close())


if __name__ == "__main__":
    sys.exit(main())
