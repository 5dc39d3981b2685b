"""`trunk_detector`: a lifecycle node that finds trunks (and posts) in the colour images the odometry node
selects, with the configured detector (`trunks.source`: the ONNX Mask R-CNN, or instance masks on disk).

In:  `/orchard/<side>/detect_request`  sensor_msgs/Image, a keyframe's colour image (stamp: the keyframe's); latched,
     so a detector that starts or restarts answers the request waiting for it (ros/remote_detector.py)
Out: `/orchard/<side>/trunk_detections`  orchard_mapping_msgs/TrunkDetectionArray (same stamp); an image it cannot
     read is answered with a refusal (image size 0, no detections), not left unanswered
Lifecycle: `configure` creates the detector (the ONNX session: ~1 s and ~100 MB), `activate` starts
answering, `deactivate` stops, `cleanup` releases the detector. With `autostart` (the default) the node
configures and activates itself as it starts, as the launcher has no lifecycle manager; on a full ROS
install, `ros2 lifecycle set` drives it with `autostart:=false`.
"""

from __future__ import annotations

import sys

from orchard_mapping_msgs.msg import TrunkDetectionArray
from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn
from sensor_msgs.msg import Image

from orchard_mapping.errors import OrchardMappingError
from orchard_mapping.io.bags import decode_color, header_ns
from orchard_mapping.pipeline import SIDES, trunk_detector
from orchard_mapping.ros.detections import detections_to_msg, refusal_msg
from orchard_mapping.ros.params import ConfigParameters
from orchard_mapping.ros.qos import LATCHED, REPLAY
from orchard_mapping.ros.spin import run_node

__all__ = ["TrunkDetectorNode", "detections_topic", "main", "request_topic"]


def request_topic(side: str) -> str:
    return f"/orchard/{side}/detect_request"


def detections_topic(side: str) -> str:
    return f"/orchard/{side}/trunk_detections"


class TrunkDetectorNode(LifecycleNode):
    def __init__(self) -> None:
        super().__init__("trunk_detector")
        self.params = ConfigParameters(self)
        self.declare_parameter("autostart", True)
        self._detect: dict[str, object] = {}
        self._subs: list = []
        self._pubs: dict[str, object] = {}
        self.answered = 0

    def on_configure(self, state: State) -> TransitionCallbackReturn:
        cfg = self.params.config
        try:
            self._detect = {side: trunk_detector(cfg, side) for side in SIDES}
        except OrchardMappingError as err:
            self.get_logger().error(f"cannot create the trunk detector: {err}")
            return TransitionCallbackReturn.FAILURE
        self._pubs = {side: self.create_lifecycle_publisher(TrunkDetectionArray, detections_topic(side), REPLAY)
                      for side in SIDES}
        self.get_logger().info(f"configured: trunks.source={cfg.trunks.source}")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        # latched: the request waiting for its answer reaches a detector that (re)starts after it was sent
        self._subs = [self.create_subscription(Image, request_topic(side),
                                               lambda msg, s=side: self._answer(s, msg), LATCHED) for side in SIDES]
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        for sub in self._subs:
            self.destroy_subscription(sub)
        self._subs = []
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        for pub in self._pubs.values():
            self.destroy_lifecycle_publisher(pub)
        self._pubs, self._detect = {}, {}  # the ONNX session goes with its detector
        return TransitionCallbackReturn.SUCCESS

    def _answer(self, side: str, msg: Image) -> None:
        stamp = header_ns(msg.header) / 1e9
        try:
            dets = self._detect[side](decode_color(msg), stamp)
        except OrchardMappingError as err:  # said so: the odometry node does not wait for an answer
            self.get_logger().error(f"{side} image at {stamp:.3f} s: {err}; refused")
            self._pubs[side].publish(refusal_msg(stamp, msg.header.frame_id))
            return
        self._pubs[side].publish(detections_to_msg(dets, stamp, msg.header.frame_id, msg.width, msg.height))
        self.answered += 1
        if self.answered == 1 or self.answered % 10 == 0:
            self.get_logger().info(f"answered {self.answered} requests")


def _make() -> TrunkDetectorNode:
    node = TrunkDetectorNode()
    if node.get_parameter("autostart").value:
        node.trigger_configure()
        node.trigger_activate()
    return node


def main(argv: list[str] | None = None) -> int:
    return run_node(_make, "trunk_detector")


if __name__ == "__main__":
    sys.exit(main())
