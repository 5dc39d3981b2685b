"""The odometry node's side of the trunk detector node: `detect(colour, stamp)` as `pipeline.EarlyDetections`
calls it, answered by the `trunk_detector` node over topics (request: the keyframe's colour image;
answer: the detections with the same stamp).

When the detector node is down (no subscriber to the requests), or does not answer within `timeout_s`, the
call returns None: the keyframe is not cleaned and the trunks near it are flagged
(`detector_unavailable_nearby`). After such a miss the next calls do not wait for a detector to appear,
only for an answer, until one comes again: a dead detector costs each later keyframe nothing, a restarted
one is used as soon as it is back.
"""

from __future__ import annotations

import threading
import time

import numpy as np
from orchard_mapping_msgs.msg import TrunkDetectionArray
from rclpy.node import Node
from sensor_msgs.msg import Image

from orchard_mapping.io.bags import header_ns
from orchard_mapping.ros.detections import detections_from_msg
from orchard_mapping.ros.messages import stamp_header
from orchard_mapping.ros.qos import REPLAY
from orchard_mapping.ros.trunk_detector import detections_topic, request_topic

__all__ = ["RemoteDetector"]


class RemoteDetector:
    def __init__(self, node: Node, side: str, frame_id: str, timeout_s: float = 5.0, wait_s: float = 15.0) -> None:
        self.side, self.frame_id, self.timeout_s, self.wait_s = side, frame_id, timeout_s, wait_s
        self._pub = node.create_publisher(Image, request_topic(side), REPLAY)
        self._sub = node.create_subscription(TrunkDetectionArray, detections_topic(side), self._on_answer, REPLAY)
        self._answers: dict[int, TrunkDetectionArray] = {}
        self._cv = threading.Condition()
        self._missed = False  # the last call got no answer
        self.unanswered = 0

    def _on_answer(self, msg: TrunkDetectionArray) -> None:
        with self._cv:
            self._answers[header_ns(msg.header)] = msg
            self._cv.notify_all()

    def _request(self, color: np.ndarray, stamp: float) -> tuple[Image, int]:
        img = Image()
        stamp_header(img.header, stamp, self.frame_id)
        img.height, img.width = int(color.shape[0]), int(color.shape[1])
        img.encoding, img.is_bigendian, img.step = "rgb8", 0, 3 * img.width
        img.data = np.ascontiguousarray(color, np.uint8).tobytes()
        return img, header_ns(img.header)

    def __call__(self, color: np.ndarray, stamp: float):
        img, key = self._request(color, stamp)
        # a detector must be listening: wait for one (it may be starting or restarting), unless the last call
        # already went unanswered
        deadline = time.monotonic() + (0.0 if self._missed else self.wait_s)
        while self._pub.get_subscription_count() == 0:
            if time.monotonic() >= deadline:
                return self._miss()
            time.sleep(0.05)
        with self._cv:
            self._pub.publish(img)
            if not self._cv.wait_for(lambda: key in self._answers, timeout=self.timeout_s):
                return self._miss()
            msg = self._answers.pop(key)
        self._missed = False
        return detections_from_msg(msg)

    def _miss(self) -> None:
        self._missed = True
        self.unanswered += 1
        return None
