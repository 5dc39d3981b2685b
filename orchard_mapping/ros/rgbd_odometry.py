"""`rgbd_odometry`: the camera topics in, each side's odometry and, when the side ends, its side map out.

Per side it runs the same `SideSession` as `orchard-map run`: the front end on each frame as it comes,
each keyframe's images spooled to disk and, every trunks.detect_every_m, handed to the trunk detector on a
thread of its own; when the side ends (the side topic changes or says `end`) loop
detection, bundle adjustment, TSDF fusion, trunk cylinders and local grounds run in
a child process (ros/finisher.py: in a thread they held the GIL for seconds and camera frames were lost),
started as the side began, while the next side is already being tracked; each side has its own, so a side's
map does not wait for the one before it. With `ground_fitter:=node` (what `orchard-map launch` sets)
the trunks' local grounds come from the `local_ground_fitter` node: once the side is fused its geometry
goes out on `side_geometry`, and the trunk cylinders are fitted against the grounds that come back on
`local_grounds` (core.trunks: the grounds, then the cylinders; `orchard-map run` does both in one process).

In:  colour and aligned depth (sensor_msgs/Image, sensor-data QoS), CameraInfo, the side topic
     (std_msgs/String "front" / "back" / "end"; without one the `side` parameter names the side, and
     without either, or with input.side_source=trajectory, the camera's U-turn round the row end does:
     core.sides, as `orchard-map run` does for one bag of a whole drive).
Out, per side (`/orchard/<side>/...`):
     odometry   nav_msgs/Odometry, every frame placed (frame odom_<side>, child the camera frame)
     path       nav_msgs/Path of the keyframes, as they are made (latched)
     keyframes  the optimised keyframe poses, nav_msgs/Path, when the side ends (latched)
     cloud      the fused cloud, sensor_msgs/PointCloud2 x y z rgb, odom_<side> (latched)
     trunk_cylinders  orchard_mapping_msgs/TrunkCylinderArray (latched)
     local_grounds    orchard_mapping_msgs/LocalGroundArray (latched; with ground_fitter:=node the
                      local_ground_fitter publishes it, and this node reads it)
     side_geometry    orchard_mapping_msgs/SideMap, a core.sidemap.SideGeometry payload: keyframe poses, fused
                      cloud, the detector's keyframes (latched; only with ground_fitter:=node)
     side_map   orchard_mapping_msgs/SideMap: the whole side map for the side merger (latched)
     status     std_msgs/String JSON: frames received, paired, processed, dropped (latched)
and on /tf the camera frame in odom_<side>, every frame placed (the same pose as `odometry`).
Frames are decoded in the subscription callback and queued (never dropped by the node; a frame DDS lost
never reaches it, and is counted from the player's side, see benchmarks/live.py).
"""

from __future__ import annotations

import array
import json
import os
import queue
import sys
import threading
import time
import traceback
import uuid
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry, Path as PathMsg
from orchard_mapping_msgs.msg import LocalGroundArray, SideMap as SideMapMsg, TrunkCylinderArray
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import String

from orchard_mapping.core.geometry import matrix_to_quat
from orchard_mapping.core.sidemap import SideMap
from orchard_mapping.core.sides import SIDE_END, SideSplitter
from orchard_mapping.errors import OrchardMappingError
from orchard_mapping.io.bags import camera_intrinsics, decode_frame, header_ns
from orchard_mapping.io.pairing import Marker, Paired, RGBDPairer
from orchard_mapping.io.sidemap_codec import (
    SIDE_GEOMETRY_ENCODING,
    SIDE_MAP_ENCODING,
    decode_side_map,
    encode_side_map,
)
from orchard_mapping.pipeline import SIDES, SideSession, SpooledKeyframeImages, Timings
from orchard_mapping.ros.clouds import cloud_to_msg
from orchard_mapping.ros.finisher import FinishingProcess, GeometryInfo, SideFinishError, finish_in_child
from orchard_mapping.ros.local_ground_fitter import geometry_topic, grounds_topic
from orchard_mapping.ros.messages import (
    TrunkRecord,
    ground_records,
    grounds_to_msg,
    stamp_header,
    trunk_grounds_from_msg,
    trunks_to_msg,
)
from orchard_mapping.ros.params import ConfigParameters
from orchard_mapping.ros.player import STATUS_TOPIC as PLAYER_STATUS
from orchard_mapping.ros.qos import CAMERA, CAMERA_REPLAYED, LATCHED
from orchard_mapping.ros.remote_detector import DETECTOR_GUARD_S, RemoteDetector
from orchard_mapping.ros.spin import StopNode, run_node
from orchard_mapping.ros.supervisor import SCRATCH_ENV
from orchard_mapping.ros.tf import Transforms, transform_msg

__all__ = ["RGBDOdometryNode", "main"]


def _pose(msg_pose, T: np.ndarray) -> None:
    q = matrix_to_quat(T[:3, :3])  # x y z w
    msg_pose.position.x, msg_pose.position.y, msg_pose.position.z = (float(v) for v in T[:3, 3])
    msg_pose.orientation.x, msg_pose.orientation.y, msg_pose.orientation.z, msg_pose.orientation.w = (
        float(v) for v in q)


@dataclass
class _Counts:
    colour: int = 0
    depth: int = 0
    paired: int = 0
    unpaired: int = 0  # colour images with no depth image within input.max_pair_dt_s
    processed: dict[str, int] = field(default_factory=dict)
    finished: list[str] = field(default_factory=list)
    # colour images the camera's own rhythm says are missing (a gap of n periods: n - 1 missed), counted
    # from the stamps received: frames DDS lost never reach the node, but their absence shows
    missed: int = 0
    # colour images a bag player says it sent and this node never received (all bags so far)
    lost_vs_player: int = 0
    side_map_latency_s: dict[str, float] = field(default_factory=dict)  # s, a side's end -> its map published
    finish_stages_s: dict[str, dict[str, float]] = field(default_factory=dict)  # side -> stage -> s (pipeline.Timings)
    failed: list[str] = field(default_factory=list)  # sides whose map could not be made
    # sides whose trunks' grounds were fitted here, the local_ground_fitter node not answering (the same grounds)
    grounds_here: list[str] = field(default_factory=list)


class RGBDOdometryNode(Node):
    def __init__(self) -> None:
        super().__init__("rgbd_odometry")
        self.params = ConfigParameters(self)
        self.declare_parameter("side", "")  # the side being recorded when no side topic says ("front"/"back")
        # where keyframe images wait for fusion ("": the graph's scratch folder under `orchard-map launch`, which
        # the supervisor removes when the graph ends, else the system's temporary folder)
        self.declare_parameter("spool_dir", "")
        # replaying bags: exit (code 0) once this many side maps are published (0: run until stopped)
        self.declare_parameter("exit_after_sides", 0)
        # the camera topics come from the project's bag player: read them reliably (ros/qos.py)
        self.declare_parameter("replayed_camera", False)
        # "node": the trunk_detector node answers (the graph); "local": the configured detector in this process
        self.declare_parameter("detector", "local")
        # s: a guard against a trunk_detector node gone for good, not a cut-off: a keyframe waits for the answer
        # to its own request (latched: a restarted detector answers it), however late (ros/remote_detector.py).
        # Only when none comes within this long does it go without detections (its trunks flagged). A deadline of
        # 5 s once left a request of the 2-tree drive unanswered in 2 of 5 test runs on a loaded machine.
        self.declare_parameter("detector_guard_s", DETECTOR_GUARD_S)
        # "node": the local_ground_fitter node fits the trunks' local grounds (the graph); "local": this node does
        self.declare_parameter("ground_fitter", "local")
        # s to wait for the local_ground_fitter's answer before this node fits the grounds itself. Not a result's
        # cut-off: the same fit gives the same grounds here, only later. A 10-tree side takes it a few seconds.
        self.declare_parameter("ground_fitter_timeout_s", 120.0)
        self._detectors: dict[str, RemoteDetector] = {}
        cfg = self.params.config
        topics = cfg.input.topics
        self.counts = _Counts()
        # colour images waiting for their depth partner, side changes in their place (io.pairing: read_rgbd's rule)
        self._pairer = RGBDPairer(round(cfg.input.max_pair_dt_s * 1e9))
        self._last_colour_ns: int | None = None
        self._steps: deque = deque(maxlen=30)  # ns between consecutive colour stamps
        self._info: CameraInfo | None = None
        self._side: str = self.get_parameter("side").value or ""
        self._work: queue.Queue = queue.Queue()  # frames and side changes, in arrival order
        self._finish: queue.Queue = queue.Queue()  # sessions whose side is over
        self._pubs: dict[str, dict[str, object]] = {}
        self._path: dict[str, PathMsg] = {}
        self.side_maps: dict[str, SideMap] = {}
        self.errors: list[str] = []
        # What the status acknowledges to a bag player before and after a side change (ros/player.py): the header
        # stamp of the last message received on each camera topic, the last side message; which run of this node
        # it is (a restarted node has not received what was sent before it started)
        self.incarnation = uuid.uuid4().hex[:12]
        self._received_ns: dict[str, int | None] = {topics.color: None, topics.depth: None}
        self._last_side: str | None = None
        self._statement: tuple[int, dict[str, int]] | None = None  # the player's last, not yet acknowledged
        self._status = self.create_publisher(String, "/orchard/odometry/status", LATCHED)
        self._tf = Transforms(self)
        # the local_ground_fitter's latest answer per side, and a condition the finishing thread waits on for it
        self._grounds: dict[str, object] = {}
        self._grounds_cv = threading.Condition()
        self._ground_node = self.get_parameter("ground_fitter").value == "node"
        if self.get_parameter("ground_fitter").value not in ("node", "local"):
            raise OrchardMappingError(f"parameter ground_fitter must be 'node' or 'local', got "
                                      f"{self.get_parameter('ground_fitter').value!r}")
        if self._ground_node:
            for side in SIDES:
                self.create_subscription(LocalGroundArray, grounds_topic(side),
                                         lambda msg, side=side: self._on_grounds(side, msg), LATCHED)
        camera = CAMERA_REPLAYED if self.get_parameter("replayed_camera").value else CAMERA
        self.create_subscription(Image, topics.color, self._on_colour, camera)
        self.create_subscription(Image, topics.depth, self._on_depth, camera)
        self.create_subscription(CameraInfo, topics.camera_info, self._on_info, camera)
        self.create_subscription(String, topics.side, self._on_side, LATCHED)
        self.create_subscription(String, PLAYER_STATUS, self._on_player, LATCHED)
        # the process that will finish the side being tracked, started as the side begins (_prepare_finishing)
        self._spare: FinishingProcess | None = None
        self._spare_closed = False
        self._spare_lock = threading.Lock()
        self._finished_lock = threading.Lock()  # sides finished on threads of their own publish one at a time
        self._threads = [threading.Thread(target=self._track_loop, daemon=True),
                         threading.Thread(target=self._finish_loop, daemon=True)]
        for t in self._threads:
            t.start()
        self._done = threading.Event()
        self.create_timer(0.2, self._check_done)
        self._publish_status()  # this incarnation is up
        self._republish_saved()

    def _check_done(self) -> None:
        if self._done.is_set():
            raise StopNode(1 if self.counts.failed else 0)

    # -- publishers

    def _side_pubs(self, side: str) -> dict[str, object]:
        if side not in self._pubs:
            base = f"/orchard/{side}"
            self._pubs[side] = {
                "odometry": self.create_publisher(Odometry, f"{base}/odometry", 10),
                "path": self.create_publisher(PathMsg, f"{base}/path", LATCHED),
                "keyframes": self.create_publisher(PathMsg, f"{base}/keyframes", LATCHED),
                "cloud": self.create_publisher(PointCloud2, f"{base}/cloud", LATCHED),
                "trunks": self.create_publisher(TrunkCylinderArray, f"{base}/trunk_cylinders", LATCHED),
                "side_map": self.create_publisher(SideMapMsg, f"{base}/side_map", LATCHED),
            }
            # one publisher per topic in the graph: with the ground fitter node, the grounds are its own
            if self._ground_node:
                self._pubs[side]["geometry"] = self.create_publisher(SideMapMsg, geometry_topic(side), LATCHED)
            else:
                self._pubs[side]["grounds"] = self.create_publisher(LocalGroundArray, grounds_topic(side), LATCHED)
        return self._pubs[side]

    def _publish_status(self) -> None:
        """Called from the executor and both worker threads: the mappings are copied first (dict() and list()
        copy under the GIL in one step), so a side starting meanwhile cannot change them mid-iteration."""
        c = self.counts
        detectors = list(self._detectors.items())
        msg = String()
        msg.data = json.dumps({"incarnation": self.incarnation, "received_ns": dict(self._received_ns),
                               "last_side": self._last_side,
                               "colour": c.colour, "depth": c.depth, "paired": c.paired, "unpaired": c.unpaired,
                               "missed": c.missed, "lost_vs_player": c.lost_vs_player,
                               "processed": dict(c.processed), "finished": list(c.finished),
                               "failed": list(c.failed), "grounds_here": list(c.grounds_here),
                               "side_map_latency_s": dict(c.side_map_latency_s),
                               "finish_stages_s": dict(c.finish_stages_s), "errors": list(self.errors),
                               "detector_unanswered": {s: d.unanswered for s, d in detectors},
                               "detector_refused": {s: d.refused for s, d in detectors},
                               "detector_guard_expired": {s: d.guard_expired for s, d in detectors}})
        self._status.publish(msg)

    # -- input (executor thread): decode, pair, queue

    def _on_info(self, msg: CameraInfo) -> None:
        self._info = msg
        self._pair()  # frames that came before the first CameraInfo (another topic: either may come first)

    def _on_side(self, msg: String) -> None:
        side = msg.data.strip()
        self._last_side = side
        if side != SIDE_END and side not in SIDES:
            self.get_logger().error(f"side topic: {side!r} is not one of {SIDES + (SIDE_END,)}; ignored")
            self._publish_status()  # received: the player's acknowledgement
            return
        self._last_colour_ns = None  # a new recording: its stamps need not follow the last one's
        self._steps.clear()
        # The change waits behind the colour images that came before it, which still wait for their depth: a side
        # message inside a bag (a drive's U-turn) is published with the frame before it, and under load that
        # frame's depth image (1.2 MB) came after it (the frame was dropped in 2 of 5 test runs on a loaded
        # machine when the side message flushed the pairing). The end of a recording flushes: no depth follows.
        self._pairer.add_marker(side)
        self._pair(flush=side == SIDE_END)
        self._publish_status()  # the side change is in its place: the player's acknowledgement to go on

    def _on_player(self, msg: String) -> None:
        """A bag player's status before a side change: what it published, and the stamp of the last message on
        each camera topic. Once those last messages are here (`_acknowledge`), the colour images this node never
        received are lost, and the status says so: the player's acknowledgement to go on with the side change."""
        try:
            statement = json.loads(msg.data)
            sent = int(statement["published"].get(self.params.config.input.topics.color, 0))
            last = {str(t): int(ns) for t, ns in (statement.get("last_ns") or {}).items()}
        except (ValueError, KeyError, TypeError, AttributeError):
            self.get_logger().warning(f"unreadable player status: {msg.data[:200]!r}")
            return
        self._statement = (sent, last)
        self._acknowledge()

    def _acknowledge(self) -> None:
        """The player's last statement, once this node received the last message it names on each camera topic:
        count the colour images lost and publish the status (the player's acknowledgement)."""
        if self._statement is None:
            return
        sent, last = self._statement
        if any(self._received_ns.get(t) != ns for t, ns in last.items() if t in self._received_ns):
            return
        self._statement = None
        lost = sent - self.counts.colour
        if lost > self.counts.lost_vs_player:
            self.get_logger().warning(f"{lost} colour image(s) the player sent never arrived")
        self.counts.lost_vs_player = max(lost, 0)
        self._publish_status()

    def _on_colour(self, msg: Image) -> None:
        self.counts.colour += 1
        ns = header_ns(msg.header)
        self._count_missed(ns)
        self._pairer.add_colour(ns, msg)
        self._pair()
        self._received_ns[self.params.config.input.topics.color] = ns
        self._acknowledge()

    def _count_missed(self, ns: int) -> None:
        """Colour stamps more than 1.5 camera periods apart (the period: the median of the last 30 steps) mean
        images were lost on the way: count them and say so (a replay faster than the node can take, a
        congested link)."""
        if self._last_colour_ns is not None and ns > self._last_colour_ns:
            dt = ns - self._last_colour_ns
            if len(self._steps) >= 10:
                period = float(np.median(self._steps))
                if dt > 1.5 * period:
                    n = int(round(dt / period)) - 1
                    self.counts.missed += n
                    self.get_logger().warning(f"{n} colour image(s) missing before stamp {ns / 1e9:.3f} s "
                                              f"({self.counts.missed} so far)")
                    dt = int(period)  # a gap is not a step of the camera's rhythm
            self._steps.append(dt)
        self._last_colour_ns = ns

    def _on_depth(self, msg: Image) -> None:
        self.counts.depth += 1
        ns = header_ns(msg.header)
        self._pairer.add_depth(ns, msg)
        self._pair()
        self._received_ns[self.params.config.input.topics.depth] = ns
        self._acknowledge()

    def _pair(self, flush: bool = False) -> None:
        """Hand on what the pairing can decide now (io.pairing, as `read_rgbd` pairs a bag's images); frames
        wait for the first CameraInfo."""
        for ev in self._pairer.pop(flush=flush, hold=self._info is None):
            if isinstance(ev, Marker):
                self._work.put(("side", ev.item))
            elif isinstance(ev, Paired):
                self.counts.paired += 1
                self._work.put(("frame", (ev.colour, ev.depth, self._info)))
            else:
                self.counts.unpaired += 1
                held = (f"{ev.depth_held_ns[0] / 1e9:.3f}-{ev.depth_held_ns[1] / 1e9:.3f} s" if ev.depth_held_ns
                        else "none")
                self.get_logger().warning(
                    f"colour image at stamp {ev.colour_ns / 1e9:.3f} s: no depth image within "
                    f"{self._pairer.max_dt_ns / 1e9:.3f} s ({'at the end of a recording' if ev.flushed else 'a later depth came first'}; "
                    f"depth stamps held {held}): frame dropped")

    # -- tracking (worker thread)

    def _track_loop(self) -> None:
        session: SideSession | None = None
        # the side of each frame and where a side ends: input.side_source's rule, as `orchard-map run` reads a drive
        sides = SideSplitter(self.params.config.input.side_source, self._side)
        beyond_first_row = False
        while True:
            kind, item = self._work.get()
            if kind == "stop":
                if session is not None:
                    self._finish.put((session, time.monotonic()))
                self._finish.put(None)
                return
            if kind == "side":
                if sides.on_label(item) and session is not None:
                    self._finish.put((session, time.monotonic()))
                    session = None
                continue
            side = sides.side()
            if not side:
                self._error("a frame came before any side was named (side topic or the `side` parameter; "
                            "input.side_source: topic)")
                continue
            if sides.row() > 1:
                # A drive along a block turned into its next row. The graph's topics and the side merger hold one
                # row's two sides: mapping the next row's as "front" and "back" again would merge it with this
                # row's. Its frames are left to `orchard-map run` on the recording, which maps every row.
                if not beyond_first_row:
                    beyond_first_row = True
                    self._error("the drive turned into a second row: the live graph maps one row; its frames "
                                "from here on are not tracked (`orchard-map run` on the recording maps every "
                                "row of a block)")
                continue
            colour, depth, info = item
            try:
                session = session or self._new_session(side, colour, info)
                frame = decode_frame(colour, depth, session.intrinsics, session.frames, side,
                                     (self.params.config.input.depth_min_m, self.params.config.input.depth_max_m),
                                     "camera topics", self.params.config.input.topics)
                pose, new = session.add(frame)
            except OrchardMappingError as err:
                self._error(str(err))
                continue
            except Exception as err:  # noqa: BLE001 - a bug must not stop the tracking thread silently
                at = header_ns(colour.header) / 1e9
                self._error(f"{side} side, frame at {at:.3f} s: {type(err).__name__}: {err}")
                self.get_logger().error(traceback.format_exc())
                continue
            self.counts.processed[side] = self.counts.processed.get(side, 0) + 1
            self._publish_pose(side, frame.stamp, pose, new)
            if sides.after_pose(pose):  # half way round the U-turn: the next side begins
                self.get_logger().info(f"{side} side ends at {frame.stamp:.3f} s: the camera turned round the row end")
                self._finish.put((session, time.monotonic()))
                session = None

    def _new_session(self, side: str, colour: Image, info: CameraInfo | None) -> SideSession:
        if info is None:
            raise OrchardMappingError("no CameraInfo received before the first frame")
        cfg = self.params.config
        intr = camera_intrinsics(info, colour.width, colour.height, "camera topics", cfg.input.topics.camera_info)
        spool = self.get_parameter("spool_dir").value or None
        if spool is None and os.environ.get(SCRATCH_ENV):  # the graph's scratch folder: reaped, then removed
            spool = str(Path(os.environ[SCRATCH_ENV]) / "rgbd_odometry")
        self._path[side] = PathMsg()
        stamp_header(self._path[side].header, 0.0, getattr(cfg.frames, f"odom_{side}"))
        self.get_logger().info(f"{side} side: tracking")
        detect = None
        if self.get_parameter("detector").value == "node":
            if side not in self._detectors:  # one client per side: each would add a publisher and a subscription
                self._detectors[side] = RemoteDetector(
                    self, side, cfg.frames.camera, guard_s=float(self.get_parameter("detector_guard_s").value))
            detect = self._detectors[side]
        session = SideSession(side, intr, cfg, SpooledKeyframeImages(spool), bag=f"{side} side (camera topics)",
                              detect=detect)
        self._prepare_finishing()
        return session

    def _publish_pose(self, side: str, stamp: float, T: np.ndarray, keyframe: bool) -> None:
        if not np.isfinite(T).all():
            return
        pubs = self._side_pubs(side)
        frame_id = getattr(self.params.config.frames, f"odom_{side}")
        odom = Odometry()
        stamp_header(odom.header, stamp, frame_id)
        odom.child_frame_id = self.params.config.frames.camera
        _pose(odom.pose.pose, T)
        pubs["odometry"].publish(odom)
        self._tf.send(transform_msg(T, frame_id, odom.child_frame_id, stamp))
        if keyframe:
            ps = PoseStamped()
            stamp_header(ps.header, stamp, frame_id)
            _pose(ps.pose, T)
            path = self._path[side]
            path.header.stamp = ps.header.stamp
            path.poses.append(ps)
            pubs["path"].publish(path)

    def _error(self, text: str) -> None:
        self.get_logger().error(text)
        self.errors.append(text)
        self._publish_status()

    # -- finishing a side (worker thread)

    def _finish_loop(self) -> None:
        try:
            self._finish_sides()
        finally:
            with self._spare_lock:
                spare, self._spare, self._spare_closed = self._spare, None, True
            if spare is not None:
                spare.close()

    def _prepare_finishing(self) -> None:
        """Start the process that will finish the side now being tracked (ros/finisher.py: its start and imports
        are then done before the side ends). Called from the tracking thread as a side begins."""
        with self._spare_lock:
            if self._spare is None and not self._spare_closed:
                self._spare = FinishingProcess()

    def _take_finishing(self) -> FinishingProcess | None:
        """The process started for the side that ended (None: finish_in_child starts one)."""
        with self._spare_lock:
            process, self._spare = self._spare, None
        return process

    def _finish_sides(self) -> None:
        # Each side is finished on a thread of its own, as soon as it ends: one after the other, the back side
        # waited for the front side's finishing, which the back side's tracking slows (10-tree row at 1x: the
        # front side's took 63 s of work beside the camera, the back side's map came 59 s after its end, 19 s
        # of them waiting). A side that comes again (a replay looping round) waits for its earlier finishing.
        running: dict[str, threading.Thread] = {}
        try:
            while True:
                item = self._finish.get()
                if item is None:
                    return
                session, ended = item
                earlier = running.get(session.side)
                if earlier is not None:
                    earlier.join()
                running[session.side] = threading.Thread(target=self._finish_side, args=(session, ended),
                                                         name=f"finish-{session.side}", daemon=True)
                running[session.side].start()
        finally:
            for t in running.values():
                t.join()

    def _finish_side(self, session: SideSession, ended: float) -> None:
        side = session.side
        self.get_logger().info(f"{side} side ended after {session.frames} frames: bundle adjustment, fusion, "
                               "trunks")
        timings = Timings()
        try:
            sm = finish_in_child(session, timings, self._ask_ground_fitter if self._ground_node else None,
                                 self._take_finishing())
        except Exception as err:  # noqa: BLE001 - reported and counted; the node goes on with the next side
            with self._finished_lock:
                self._error(f"{side} side: no side map: {err}" if isinstance(err, OrchardMappingError)
                            else f"{side} side: no side map: {type(err).__name__}: {err}")
                if isinstance(err, SideFinishError) and not err.typed:
                    self.get_logger().error(err.detail)
                elif not isinstance(err, OrchardMappingError):
                    self.get_logger().error(traceback.format_exc())
                self.counts.failed.append(side)
                self._check_wanted()
            return
        with self._finished_lock:
            self.side_maps[side] = sm
            self._publish_side_map(sm)
            self.counts.finished.append(side)
            self.counts.side_map_latency_s[side] = round(time.monotonic() - ended, 3)
            self.counts.finish_stages_s[side] = {k: round(v, 3) for k, v in timings.stages.items()}
            self._publish_status()
            stages = ", ".join(f"{k.removesuffix('_' + side)} {v:.1f}" for k, v in timings.stages.items()
                               if not k.startswith(("front_end", "trunk_detection")))
            self.get_logger().info(f"{side} side map published {self.counts.side_map_latency_s[side]:.1f} s after "
                                   f"the side ended: {len(sm.keyframe_poses)} keyframes, {len(sm.cloud_points)} "
                                   f"points, {len(sm.trunks)} trunks (finishing, s: {stages})")
            self._check_wanted()

    # -- the trunks' grounds from the local_ground_fitter node

    def _on_grounds(self, side: str, msg: LocalGroundArray) -> None:
        with self._grounds_cv:
            self._grounds[side] = msg
            self._grounds_cv.notify_all()

    def _ask_ground_fitter(self, info: GeometryInfo, data: bytes):
        """Publish a side's geometry and wait for the local_ground_fitter's grounds of it (core.trunks.TrunkGround
        per landmark); None, to fit them in the side's finishing process, when none came within
        ground_fitter_timeout_s or the answer was unreadable. Called from the finishing thread."""
        side = info["side"]
        msg = SideMapMsg()
        stamp_header(msg.header, float(info["stamp"]), info["frame_id"])
        msg.side, msg.encoding = side, SIDE_GEOMETRY_ENCODING
        msg.keyframes, msg.trunks, msg.cloud_points = int(info["keyframes"]), 0, int(info["cloud_points"])
        msg.data = array.array("B", data)
        want = (msg.header.stamp.sec, msg.header.stamp.nanosec)

        def answered() -> bool:
            m = self._grounds.get(side)
            return m is not None and (m.header.stamp.sec, m.header.stamp.nanosec) == want

        with self._grounds_cv:
            self._grounds.pop(side, None)  # an earlier answer (a replay looping round) is not this one's
        self._side_pubs(side)["geometry"].publish(msg)
        timeout = float(self.get_parameter("ground_fitter_timeout_s").value)
        with self._grounds_cv:
            got = self._grounds_cv.wait_for(answered, timeout=timeout)
            answer = self._grounds.get(side) if got else None
        try:
            if answer is not None:
                return trunk_grounds_from_msg(answer)[2]
            why = f"no answer within {timeout:g} s"
        except OrchardMappingError as err:
            why = str(err)
        self.get_logger().warning(f"{side} side: local grounds from the local_ground_fitter: {why}; they are "
                                  "fitted here (the same fit)")
        self.counts.grounds_here.append(side)
        return None

    def _check_wanted(self) -> None:
        """Replaying bags: stop once every side expected has its map or has failed (exit code 1 if one failed)."""
        wanted = self.get_parameter("exit_after_sides").value
        if wanted and len(self.counts.finished) + len(self.counts.failed) >= wanted:
            self._done.set()

    def _saved_map(self, side: str) -> Path | None:
        """Where a published side map is kept for a restarted node (the graph's scratch folder; None without)."""
        scratch = os.environ.get(SCRATCH_ENV)
        return Path(scratch) / "rgbd_odometry" / f"side_map_{side}.bin" if scratch else None

    def _republish_saved(self) -> None:
        """Publish again the side maps a killed predecessor published (kept in the graph's scratch folder): a
        latched message goes with its publisher, and a side merger started later would not get them. Not
        counted as finished here: a replay maps them again (the player starts again with this node)."""
        for side in SIDES:
            path = self._saved_map(side)
            if path is None or not path.is_file():
                continue
            try:
                sm = decode_side_map(path.read_bytes(), str(path))
            except OrchardMappingError as err:
                self.get_logger().warning(f"the {side} side map kept by a predecessor is unreadable: {err}")
                continue
            self._publish_side_map(sm, save=False)
            self.get_logger().info(f"{side} side map published again (this node's predecessor made it)")

    def _publish_side_map(self, sm: SideMap, save: bool = True) -> None:
        pubs = self._side_pubs(sm.side)
        path = PathMsg()
        stamp = float(sm.keyframe_stamps[-1])
        stamp_header(path.header, stamp, sm.frame_id)
        for t, T in zip(sm.keyframe_stamps, sm.keyframe_poses, strict=True):
            ps = PoseStamped()
            stamp_header(ps.header, float(t), sm.frame_id)
            _pose(ps.pose, T)
            path.poses.append(ps)
        pubs["keyframes"].publish(path)
        pubs["cloud"].publish(cloud_to_msg(sm.cloud_points, sm.cloud_colors, sm.frame_id, stamp))
        pubs["trunks"].publish(trunks_to_msg([TrunkRecord.from_landmark(lm, sm.side) for lm in sm.trunks],
                                             sm.frame_id, stamp))
        if "grounds" in pubs:  # else the ground fitter node published the side's grounds
            pubs["grounds"].publish(grounds_to_msg(ground_records(sm.trunks, sm.side), sm.frame_id, stamp))
        msg = SideMapMsg()
        stamp_header(msg.header, stamp, sm.frame_id)
        msg.side, msg.encoding = sm.side, SIDE_MAP_ENCODING
        msg.keyframes, msg.trunks, msg.cloud_points = len(sm.keyframe_poses), len(sm.trunks), len(sm.cloud_points)
        data = encode_side_map(sm)
        msg.data = array.array("B", data)  # from bytes at once (an iterable is copied per item)
        pubs["side_map"].publish(msg)
        path = self._saved_map(sm.side) if save else None
        if path is not None:  # for a restarted node to publish again (written whole, then moved into place)
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp")
            tmp.write_bytes(data)
            os.replace(tmp, path)

    def close(self) -> None:
        self._pair(flush=True)
        self._work.put(("stop", None))
        for t in self._threads:
            t.join(timeout=600)
        # The last status (a side finished) and the side maps are published just before the node stops: run_node
        # waits until the subscribers (the side merger, the recorder) acknowledged them (ros/spin.py).


def main(argv: list[str] | None = None) -> int:
    return run_node(RGBDOdometryNode, "rgbd_odometry", finish=lambda node: node.close())


if __name__ == "__main__":
    sys.exit(main())
