"""Helper process for test_msgs_cross_process: publishes one TrunkCylinderArray.

Usage: python trunk_publisher.py TOPIC SPEC_JSON TIMEOUT_S

Builds the message from SPEC_JSON (the dict layout of msg_spec() in the test),
waits until a subscription is matched, publishes once (reliable, transient
local, so a reader that matched a moment later still gets it), prints
"PUBLISHED" and keeps spinning until stdin closes or TIMEOUT_S passes.
Exit 0 after publishing, 2 when no subscriber matched in time.
"""

import json
import math
import sys
import threading
import time

import rclpy
from orchard_mapping_msgs.msg import TrunkCylinder, TrunkCylinderArray
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def _float(v):
    return math.nan if v == "nan" else float(v)


def build(spec: dict) -> TrunkCylinderArray:
    msg = TrunkCylinderArray()
    msg.header.frame_id = spec["frame_id"]
    msg.header.stamp.sec = spec["stamp"][0]
    msg.header.stamp.nanosec = spec["stamp"][1]
    for c in spec["cylinders"]:
        cyl = TrunkCylinder()
        cyl.header.frame_id = spec["frame_id"]
        cyl.header.stamp.sec = spec["stamp"][0]
        cyl.header.stamp.nanosec = spec["stamp"][1]
        cyl.tree_id = c["tree_id"]
        cyl.side = c["side"]
        cyl.base.x, cyl.base.y, cyl.base.z = (float(v) for v in c["base"])
        cyl.axis.x, cyl.axis.y, cyl.axis.z = (float(v) for v in c["axis"])
        cyl.radius = _float(c["radius"])
        cyl.length = _float(c["length"])
        cyl.radius_stddev = _float(c["radius_stddev"])
        cyl.fit_rmse = _float(c["fit_rmse"])
        cyl.inlier_count = c["inlier_count"]
        msg.cylinders.append(cyl)
    return msg


def main() -> int:
    topic, spec, timeout = sys.argv[1], json.loads(sys.argv[2]), float(sys.argv[3])
    stdin_closed = threading.Event()

    def watch_stdin():
        sys.stdin.read()
        stdin_closed.set()

    threading.Thread(target=watch_stdin, daemon=True).start()

    rclpy.init()
    try:
        node = rclpy.create_node("orchard_test_trunk_publisher")
        pub = node.create_publisher(TrunkCylinderArray, topic, QOS)
        deadline = time.monotonic() + timeout
        while pub.get_subscription_count() == 0:
            if time.monotonic() > deadline or stdin_closed.is_set():
                print("NO_SUBSCRIBER", flush=True)
                return 2
            rclpy.spin_once(node, timeout_sec=0.05)
        pub.publish(build(spec))
        print("PUBLISHED", flush=True)
        while not stdin_closed.is_set() and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.05)
        node.destroy_node()
        return 0
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    sys.exit(main())
