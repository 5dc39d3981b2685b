"""`recorder`: writes what the node graph publishes to an MCAP bag (rosbag2 folder), without ROS's CLI.

It subscribes to every topic under the given prefixes (default `/orchard`) as they appear, with the
QoS their publisher offers (so the latched results are received too), takes the messages as bytes
(no decode) and writes them with their receive time as log time. The bag is written into a hidden
sibling folder and moved into place when the recorder stops (SIGINT/SIGTERM): a killed recorder never
leaves a half-written bag under the given name.

At the stop it takes everything already delivered to it and then closes the bag. Under `orchard-map
launch` the recorder is stopped last, once every other node has exited, and a node exits only once its
subscribers acknowledged what it published (ros/spin.py): all of it is then in the recorder's readers, and
the recorder takes until none has anything left (no quiet time decides it; `DRAIN_AT_MOST_S` is a guard
against a stream that never ends).

A recorder killed mid-row loses nothing it wrote: each message is on disk once written (`BagWriter.flush`).
Under `orchard-map launch` the supervisor starts it again, and the new recorder carries on the same bag: it
copies what its predecessor wrote (the partial bag it left, named in the graph's scratch folder; io.salvage
reads a bag cut short) into its own, then records on. The latched topics it receives again (their last
message) are not written twice; what was published only while no recorder ran (the gap: a few poses and
transforms) is not in the bag, and the recorder says how long the gap was.

Usage: python -m orchard_mapping.ros.recorder OUT_BAG [--prefix /orchard ...] [--overwrite]
"""

from __future__ import annotations

import argparse
import os
import shutil
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
from orchard_mapping.ros.supervisor import SCRATCH_ENV

__all__ = ["Recorder", "main"]

DRAIN_AT_MOST_S = 60.0  # s, a guard: taking what arrived before the stop ends when nothing is left (_drain)


class Recorder(Node):
    def __init__(self, out: Path, prefixes: tuple[str, ...] = ("/orchard",), overwrite: bool = False,
                 poll_s: float = 0.5) -> None:
        super().__init__("recorder")
        self.prefixes = prefixes
        self.writer = BagWriter(out, overwrite=overwrite)
        self.writer.open()
        self.received: Counter[str] = Counter()
        self.carried = 0  # messages carried over from a killed predecessor's bag
        self._subs: dict[str, object] = {}
        self._dropped: set[str] = set()
        self._carried_last: dict[str, bytes] = {}  # topic -> the predecessor's last message on it
        scratch = os.environ.get(SCRATCH_ENV)
        # the graph's scratch folder names the partial bag being written, for a restarted recorder to carry on
        self._note = Path(scratch) / "recorder" / f"{Path(out).name}.partial" if scratch else None
        if self._note is not None:
            self._carry_on()
            self._note.parent.mkdir(parents=True, exist_ok=True)
            self._note.write_text(str(self.writer.partial))
        self.create_timer(poll_s, self._discover)

    def _carry_on(self) -> None:
        """Copy what a killed predecessor wrote (its partial bag, named in the scratch folder) into this bag."""
        if not self._note.is_file():
            return
        old = Path(self._note.read_text().strip())
        if not old.is_dir() or old == self.writer.partial:
            return
        from mcap.reader import make_reader

        from orchard_mapping.errors import BagReadError
        from orchard_mapping.io.salvage import salvage_mcap

        last_ns = None
        for src in sorted(old.rglob("*.mcap")):
            dst = self._note.parent / f"salvaged-{os.getpid()}-{src.name}"
            try:
                salvaged = salvage_mcap(src, dst)
            except BagReadError as err:
                self.get_logger().warning(f"nothing to carry over from the killed recorder's {src}: {err}")
                continue
            with open(dst, "rb") as f:
                for schema, channel, message in make_reader(f).iter_messages(log_time_order=False):
                    self.writer.write_raw(channel.topic, message.log_time / 1e9, message.data, schema.name)
                    self._carried_last[channel.topic] = bytes(message.data)
                    self.received[channel.topic] += 1
                    self.carried += 1
            last_ns = salvaged.last_log_time_ns
            dst.unlink(missing_ok=True)
        self.writer.flush()
        shutil.rmtree(old, ignore_errors=True)
        gap = (f"; nothing recorded for {self.get_clock().now().nanoseconds / 1e9 - last_ns / 1e9:.1f} s before this "
               "start (the gap)" if last_ns is not None else "")
        self.get_logger().warning(f"carried on the bag of a recorder that was killed: {self.carried} messages "
                                  f"it wrote{gap}")

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
        data = bytes(data)
        if self._carried_last and self._carried_last.pop(topic, None) == data:
            return  # a latched message the predecessor wrote, received again: written once
        now = self.get_clock().now().nanoseconds / 1e9
        try:
            self.writer.write_raw(topic, now, data, msgtype)
            self.writer.flush()  # on disk: a killed recorder loses nothing it wrote
        except BagError as err:  # a type the bag's type store does not know: say so once, go on with the rest
            self.get_logger().error(f"{topic} is not recorded: {err}")
            self._dropped.add(topic)
            return
        self.received[topic] += 1

    def _drain(self, at_most_s: float = DRAIN_AT_MOST_S, idle_polls: int = 3) -> None:
        """At the stop, take what already arrived (behind a large side map the executor may be seconds behind)
        until no reader has anything left: `idle_polls` polls in a row that take nothing (a poll takes one
        ready message or timer without waiting). at_most_s only guards against a stream that never ends."""
        end = time.monotonic() + at_most_s
        idle = 0
        try:
            while idle < idle_polls and time.monotonic() < end:
                before = sum(self.received.values())
                rclpy.spin_once(self, timeout_sec=0.0)
                idle = idle + 1 if sum(self.received.values()) == before else 0
        except Exception as err:  # noqa: BLE001 - a context already shut down (SIGINT): nothing more to take
            self.get_logger().debug(f"recorder drain stopped: {err}")

    def close(self) -> None:
        self._drain()
        self.writer.close()
        if self._note is not None:
            self._note.unlink(missing_ok=True)
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
