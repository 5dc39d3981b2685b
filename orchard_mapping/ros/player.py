"""`bag_player`: replays recorded rosbag2 / MCAP bags onto topics with their original timing.

`ros2 bag` is not available from PyPI, and the node graph must run on a recording exactly as on the
vehicle: this node publishes each stored message's bytes unchanged (no decode, no re-encode) at its
log time, scaled by `--rate`, from `--start` seconds into the first bag, once or `--loop`ed.

Which side each bag records: a bag that carries the side topic (`/orchard/side`) replays it as it is;
otherwise `--side front --side back` (one per bag) publishes the side when its bag starts. After each
bag the side `end` is published: the odometry node finishes a side when the side changes or ends.

Before the first message the player waits (up to `--wait`; `orchard-map launch` gives a generous guard and the
player then fails rather than play to a graph that is not there) until every camera topic has a subscriber
(with `--wait-reader NAME`, a subscription of that node: a recorder's does not count), so the first frames are not lost to discovery (0.1-3 s on loopback, measured), and until each node of
`--wait-node` is in the graph: the graph's other nodes, whose start (importing the core: seconds of both
cores) would otherwise starve the odometry node of the first frames (24 of 462 lost on the 2-tree test row). With `--stats FILE` it
writes, when done, the number of messages published per topic and the replay's wall and log time
(atomically, JSON), which a benchmark compares with what the nodes processed.

Side changes by acknowledgement (`--side-acks`, what `orchard-map launch` sets). The side topic and the camera
topics are delivered independently, and a loaded subscriber may take them in another order than they were
sent. So before a side change the player publishes its status, with the stamp of the last message it sent on
each camera topic, and waits until the odometry node's status (`/orchard/odometry/status`) says it received
those messages; after the change, until the status names the side received. The order the odometry node sees
is then the bag's, however late it is (a pause of 0.5 s either side of the change, the rule before, failed to
keep it on a loaded machine). A restarted odometry node (another `incarnation` in its status) cannot have the
messages sent before it started: its first status acknowledges them. `--ack-guard` is only a guard against an
odometry node that is gone for good (counted as `ack_guard_expired` in the status).

Usage: python -m orchard_mapping.ros.player BAG [BAG ...] [--rate R] [--start S] [--loop]
           [--side front --side back] [--wait S] [--wait-node NAME ...] [--wait-reader NAME ...]
           [--side-acks] [--ack-guard S] [--stats FILE]
"""

from __future__ import annotations

import argparse
import importlib
import json
import struct
import sys
import time
from collections import Counter
from pathlib import Path

import rclpy
from rclpy.node import Node
from rclpy.utilities import remove_ros_args
from std_msgs.msg import String

from orchard_mapping.config import TopicsConfig
from orchard_mapping.core.sides import SIDE_END
from orchard_mapping.errors import BagError, OrchardMappingError
from orchard_mapping.io.bags import describe_bag, iter_raw
from orchard_mapping.io.results import atomic_write_text
from orchard_mapping.ros.qos import LATCHED, REPLAY

__all__ = ["SIDE_END", "STATUS_TOPIC", "BagPlayer", "main", "message_class"]

# s: a side change is published this long after the last message before it and before the first after it,
# so a subscriber has taken every image of one side before it hears of the next (the side and the images
# travel on different topics, and an executor may take them in either order)
SIDE_GUARD_S = 0.5
# std_msgs/String JSON after each bag: the bag, its side and the messages published per topic so far, so that
# a subscriber counts what it lost (the odometry node reports it: losses at a side's start or end leave no
# gap in the camera's rhythm to see them by)
STATUS_TOPIC = "/orchard/player/status"
# the odometry node's status, which acknowledges what it received (--side-acks)
ODOMETRY_STATUS_TOPIC = "/orchard/odometry/status"
ACK_GUARD_S = 300.0  # s, a guard against an odometry node gone for good (not a cut-off: an acknowledgement is waited for)
END_ACK_GUARD_S = 30.0  # s, at most this long at the end for the subscribers to acknowledge the last messages


def header_stamp_ns(data: bytes) -> int | None:
    """ns of the header stamp of a serialised (CDR) message that starts with a std_msgs/Header (images, camera
    info): the 4-byte encapsulation header, then int32 sec, uint32 nanosec; None if too short."""
    if len(data) < 12:
        return None
    sec, nanosec = struct.unpack_from("<iI" if data[1] & 1 else ">iI", data, 4)
    return sec * 1_000_000_000 + nanosec


class PlayerError(OrchardMappingError):
    """The player cannot replay what it was given."""


def message_class(msgtype: str) -> type:
    """The rclpy message class of a rosbags type name such as `sensor_msgs/msg/Image`."""
    try:
        pkg, kind, name = msgtype.split("/")
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    except (ValueError, ImportError, AttributeError) as err:
        raise PlayerError(f"no ROS message type {msgtype!r} in this installation: {err}") from err


class BagPlayer(Node):
    """Publishes the stored messages of bags with their original timing (see the module docstring)."""

    def __init__(self, bags: list[Path], *, rate: float = 1.0, start_s: float = 0.0, loop: bool = False,
                 sides: list[str] | None = None, topics: TopicsConfig = TopicsConfig(),  # noqa: B008
                 side_acks: bool = False, ack_guard_s: float = ACK_GUARD_S) -> None:
        super().__init__("bag_player")
        if not rate > 0:
            raise PlayerError(f"--rate must be > 0, got {rate}")
        if sides and len(sides) != len(bags):
            raise PlayerError(f"--side given {len(sides)} times for {len(bags)} bag(s): give one per bag or none")
        self.bags, self.rate, self.start_s, self.loop = bags, rate, start_s, loop
        self.sides = sides or [None] * len(bags)
        self.topics = topics
        self.published: Counter[str] = Counter()
        self.last_ns: dict[str, int] = {}  # topic -> the header stamp (ns) of the last camera message published
        self.side_acks, self.ack_guard_s = side_acks, ack_guard_s
        self.ack_guard_expired = 0
        self._odometry: dict | None = None  # the odometry node's latest status
        self._incarnations: set[str] = set()  # the odometry node's incarnations heard from
        if side_acks:
            self.create_subscription(String, ODOMETRY_STATUS_TOPIC, self._on_odometry, LATCHED)
        self._bag = ""  # the bag being played
        self._side_pub = self.create_publisher(String, topics.side, LATCHED)
        self._status_pub = self.create_publisher(String, STATUS_TOPIC, LATCHED)
        # every topic's publisher exists before the first message, so that subscribers (and a recorder
        # that follows the graph) can match before the replay starts
        self._pubs: dict[str, object] = {}
        for bag in bags:
            for topic, msgtype, _ in describe_bag(bag).topics:
                if topic != topics.side and topic not in self._pubs:
                    self._pubs[topic] = self.create_publisher(message_class(msgtype), topic, REPLAY)

    def wait_for_subscribers(self, timeout_s: float, nodes: tuple[str, ...] = (),
                             readers: tuple[str, ...] = ()) -> bool:
        """Spin until each camera topic has a subscriber (of each node named in `readers`, when given) and
        each node named in `nodes` is up (True), or timeout_s passes (False).

        `readers`: any subscriber is not enough where a recorder also listens: it may match first, and a
        frame sent before the odometry node's own reader matched is lost to it (in one CI run of many the
        odometry node's CameraInfo reader had not matched when the frames began, and it refused both
        sides: "no CameraInfo received before the first frame")."""
        wanted = [t for t in (self.topics.color, self.topics.depth, self.topics.camera_info) if t in self._pubs]
        if any(self.sides):
            wanted.append(self.topics.side)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(self._has_readers(t, readers) for t in wanted) and set(nodes) <= set(self.get_node_names()) \
                    and (not self.side_acks or self._odometry is not None):  # acknowledgements need its status
                return True
            rclpy.spin_once(self, timeout_sec=0.05)
        return False

    def _has_readers(self, topic: str, readers: tuple[str, ...]) -> bool:
        if not readers:
            return self.count_subscribers(topic) > 0
        return set(readers) <= {info.node_name for info in self.get_subscriptions_info_by_topic(topic)}

    def _on_odometry(self, msg: String) -> None:
        try:
            status = json.loads(msg.data)
        except ValueError:
            return
        if isinstance(status, dict):
            self._odometry = status

    def _await(self, what: str, acked) -> None:
        """Spin until acked(odometry status) holds (--side-acks), for at most the guard."""
        end = time.monotonic() + self.ack_guard_s
        while not (self._odometry is not None and acked(self._odometry)):
            if time.monotonic() > end:
                self.ack_guard_expired += 1
                self.get_logger().warning(f"the odometry node did not acknowledge {what} within {self.ack_guard_s:g} "
                                          "s: going on")
                return
            rclpy.spin_once(self, timeout_sec=0.05)

    def _images_acked(self, status: dict, known: set[str]) -> bool:
        """The odometry node received the last message sent on each camera topic it reads, or it is a new
        incarnation (restarted after they were sent: they are lost to it)."""
        if status.get("incarnation") not in known:
            return True
        got = status.get("received_ns") or {}
        return all(got.get(t) == self.last_ns[t] for t in got if t in self.last_ns)

    def _side_change(self, side: str, stored: bytes | None = None) -> None:
        """Publish a side change (the stored message's bytes, or `side`): with --side-acks only once the odometry
        node has everything sent before it, and return only once it has the change."""
        status = String()
        status.data = json.dumps({"bag": self._bag, "side": side, "published": dict(self.published),
                                  "last_ns": dict(self.last_ns),
                                  "ack_guard_expired": self.ack_guard_expired})
        self._status_pub.publish(status)
        if self.side_acks:
            if self._odometry is not None:
                self._incarnations.add(self._odometry.get("incarnation"))
            known = set(self._incarnations)
            self._await("the images before the side change", lambda st: self._images_acked(st, known))
        if stored is not None:
            self._side_pub.publish(stored)  # the stored bytes, through the latched publisher
        else:
            msg = String()
            msg.data = side
            self._side_pub.publish(msg)
        self.published[self.topics.side] += 1
        if self.side_acks:
            self._await(f"the side change to {side!r}", lambda st: str(st.get("last_side")).strip() == side.strip())

    def _pause(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while (left := end - time.monotonic()) > 0:
            rclpy.spin_once(self, timeout_sec=min(left, 0.05))

    def _say_side(self, side: str) -> None:
        self._pause(SIDE_GUARD_S)
        self._side_change(side)
        self._pause(SIDE_GUARD_S)

    def play(self) -> None:
        """Replay every bag once (or until interrupted with --loop)."""
        while True:
            for i, (bag, side) in enumerate(zip(self.bags, self.sides, strict=True)):
                self._play_one(bag, side, self.start_s if i == 0 else 0.0)
            if not self.loop:
                return

    def _play_one(self, bag: Path, side: str | None, start_s: float) -> None:
        self._bag = str(bag)
        if side is not None:
            self._say_side(side)
        t0_wall: float | None = None
        t0_log = 0
        for m in iter_raw(bag, start_s=start_s):
            if side is not None and m.topic == self.topics.side:
                continue  # the side given on the command line wins over the bag's
            if t0_wall is None:
                t0_wall, t0_log = time.monotonic(), m.log_time_ns
            self._pause(t0_wall + (m.log_time_ns - t0_log) / 1e9 / self.rate - time.monotonic())
            if m.topic == self.topics.side:
                self._side_change(_side_text(m.data), m.data)
                continue
            self._pubs[m.topic].publish(m.data)
            self.published[m.topic] += 1
            stamp = header_stamp_ns(m.data) if m.topic in (self.topics.color, self.topics.depth) else None
            if stamp is not None:
                self.last_ns[m.topic] = stamp
        self._say_side(SIDE_END)

    def wait_for_acks(self, guard_s: float = END_ACK_GUARD_S) -> bool:
        """Wait until every subscriber acknowledged every message published (reliable ones), for at most guard_s."""
        from rclpy.duration import Duration

        end = time.monotonic() + guard_s
        ok = True
        for pub in [self._side_pub, self._status_pub, *self._pubs.values()]:
            ok = pub.wait_for_all_acked(Duration(seconds=max(end - time.monotonic(), 0.0))) and ok
        return ok


def _side_text(data: bytes) -> str:
    """The text of a serialised std_msgs/String (CDR: encapsulation, uint32 length with the NUL, the bytes)."""
    try:
        (n,) = struct.unpack_from("<I" if data[1] & 1 else ">I", data, 4)
        return bytes(data[8:8 + n]).rstrip(b"\0").decode()
    except (struct.error, UnicodeDecodeError, IndexError):
        return ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="bag_player", description=__doc__.split("\n\n")[0])
    ap.add_argument("bags", nargs="+", type=Path)
    ap.add_argument("--rate", type=float, default=1.0, help="replay speed (2: twice as fast)")
    ap.add_argument("--start", type=float, default=0.0, help="s into the first bag to start from")
    ap.add_argument("--loop", action="store_true", help="replay until stopped")
    ap.add_argument("--side", action="append", choices=("front", "back"), help="the side each bag records")
    ap.add_argument("--wait", type=float, default=20.0, help="s to wait for subscribers to the camera topics")
    ap.add_argument("--wait-node", action="append", default=[], help="also wait until this node is up")
    ap.add_argument("--wait-reader", action="append", default=[],
                    help="wait until this node subscribes to every camera topic (not just any subscriber)")
    ap.add_argument("--side-acks", action="store_true",
                    help="publish a side change only once the odometry node acknowledged what was sent before it")
    ap.add_argument("--ack-guard", type=float, default=ACK_GUARD_S,
                    help="s to wait for an acknowledgement before going on (a guard against a node gone for good)")
    ap.add_argument("--stats", type=Path, help="write what was published (JSON) here when done")
    # `ros2 run` / `ros2 launch` append --ros-args ...: those are rclpy's (rclpy.init reads them), not ours
    args = ap.parse_args(remove_ros_args(["prog", *(sys.argv[1:] if argv is None else argv)])[1:])
    rclpy.init()
    try:
        try:
            player = BagPlayer(args.bags, rate=args.rate, start_s=args.start, loop=args.loop, sides=args.side,
                               side_acks=args.side_acks, ack_guard_s=args.ack_guard)
        except (BagError, PlayerError) as err:
            print(f"bag_player: {err}", file=sys.stderr)
            return 2
        if not player.wait_for_subscribers(args.wait, tuple(args.wait_node), tuple(args.wait_reader)):
            if args.wait_node or args.wait_reader:  # the graph asked for is not there: playing would lose frames
                print(f"bag_player: the nodes {args.wait_node} (readers {args.wait_reader}) were not all up after "
                      f"{args.wait:g} s", file=sys.stderr)
                return 2
            player.get_logger().warning(f"no subscriber to the camera topics after {args.wait} s: playing anyway")
        t0 = time.monotonic()
        try:
            player.play()
        except (BagError, PlayerError) as err:
            print(f"bag_player: {err}", file=sys.stderr)
            return 2
        wall = time.monotonic() - t0
        # the publishers go away only once every reliable subscriber acknowledged the last messages
        if not player.wait_for_acks():
            player.get_logger().warning(f"not every subscriber acknowledged the last messages within "
                                        f"{END_ACK_GUARD_S:g} s")
        if args.stats:
            atomic_write_text(args.stats, json.dumps({"published": dict(player.published), "wall_s": wall,
                                                      "rate": args.rate, "bags": [str(b) for b in args.bags]},
                                                     indent=1))
        player.get_logger().info(f"replayed {sum(player.published.values())} messages in {wall:.1f} s")
        player.destroy_node()
        return 0
    except KeyboardInterrupt:
        return 0
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
