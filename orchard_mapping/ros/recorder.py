"""`recorder`: writes what the node graph publishes to an MCAP bag (rosbag2 folder), without ROS's CLI.

It subscribes to every topic under the given prefixes (default `/orchard`) as they appear, with the
QoS their publisher offers (so the latched results are received too), takes the messages as bytes
(no decode) and writes them with their receive time as log time. The bag is written into a hidden
sibling folder and moved into place when the recorder stops (SIGINT/SIGTERM): a killed recorder never
leaves a half-written bag under the given name.

Usage: python -m orchard_mapping.ros.recorder OUT_BAG [--prefix /orchard ...] [--overwrite]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args

from orchard_mapping.errors import BagError
from orchard_mapping.io.bag_writer import BagWriter
from orchard_mapping.ros.player import message_class
from orchard_mapping.ros.spin import run_node

__all__ = ["Recorder", "main"]

DRAIN_AT_MOST_S = 5.0  # s, taking what arrived before the stop


class Recorder(Node):
    def __init__(self, out: Path, prefixes: tuple[str, ...] = ("/orchard",), overwrite: bool = False,
                 poll_s: float = 0.5) -> None:
        super().__init__("recorder")
        self.prefixes = prefixes
        self.writer = BagWriter(out, overwrite=overwrite)
        self.writer.open()
        self.received: Counter[str] = Counter()
        self._subs: dict[str, object] = {}
        self._dropped: set[str] = set()
        self.create_timer(poll_s, self._discover)

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subs or not any(topic == p or topic.startswith(p.rstrip("/") + "/")
                                              for p in self.prefixes):
                continue
            if len(types) != 1:
                self.get_logger().warning(f"{topic}: {len(types)} types published ({types}); not recorded")
                self._subs[topic] = None
                continue
            pubs = self.get_publishers_info_by_topic(topic)
            if not pubs:
                continue
            offered = pubs[0].qos_profile
            qos = QoSProfile(depth=100, reliability=offered.reliability,
                             durability=offered.durability if offered.durability in (
                                 DurabilityPolicy.TRANSIENT_LOCAL, DurabilityPolicy.VOLATILE)
                             else DurabilityPolicy.VOLATILE)
            if qos.reliability not in (ReliabilityPolicy.RELIABLE, ReliabilityPolicy.BEST_EFFORT):
                qos.reliability = ReliabilityPolicy.RELIABLE
            msgtype = types[0]  # `pkg/msg/Name`: the graph and rosbags spell types alike
            self._subs[topic] = self.create_subscription(
                message_class(msgtype), topic, lambda data, t=topic, m=msgtype: self._write(t, m, data), qos,
                raw=True)

    def _write(self, topic: str, msgtype: str, data: bytes) -> None:
        if topic in self._dropped:
            return
        now = self.get_clock().now().nanoseconds / 1e9
        try:
            self.writer.write_raw(topic, now, bytes(data), msgtype)
        except BagError as err:  # a type the bag's type store does not know: say so once, go on with the rest
            self.get_logger().error(f"{topic} is not recorded: {err}")
            self._dropped.add(topic)
            return
        self.received[topic] += 1

    def _drain(self, quiet_s: float = 0.3, at_most_s: float = DRAIN_AT_MOST_S) -> None:
        """At the stop, take what already arrived (behind a large side map the executor may be seconds
        behind: the graph stops when its last node finishes, not when the recorder caught up) until nothing
        came for quiet_s, for at most at_most_s."""
        end = time.monotonic() + at_most_s
        try:
            while time.monotonic() < end:
                before = sum(self.received.values())
                rclpy.spin_once(self, timeout_sec=quiet_s)
                if sum(self.received.values()) == before:
                    return
        except Exception as err:  # noqa: BLE001 - a context already shut down (SIGINT): nothing more to take
            self.get_logger().debug(f"recorder drain stopped: {err}")

    def close(self) -> None:
        self._drain()
        self.writer.close()
        self.get_logger().info(f"recorded {sum(self.received.values())} messages on {len(self.received)} topics "
                               f"to {self.writer.path}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="recorder", description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="the bag folder to write")
    ap.add_argument("--prefix", action="append", help="record topics under this prefix (default /orchard)")
    ap.add_argument("--overwrite", action="store_true")
    # `ros2 run` / `ros2 launch` append --ros-args ...: those are rclpy's (rclpy.init reads them), not ours
    args = ap.parse_args(remove_ros_args(["prog", *(sys.argv[1:] if argv is None else argv)])[1:])
    return run_node(lambda: Recorder(args.out, tuple(args.prefix or ["/orchard"]), args.overwrite), "recorder",
                    finish=lambda node: node.close())


if __name__ == "__main__":
    sys.exit(main())
