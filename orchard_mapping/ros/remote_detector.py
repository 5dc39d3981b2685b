"""The odometry node's side of the trunk detector node: `detect(colour, stamp)` as `pipeline.EarlyDetections`
calls it, answered by the `trunk_detector` node over topics (request: the keyframe's colour image;
answer: the detections with the same stamp).

What decides the answer is the messages, not the clock (a replay gives the same trees on an idle and on a
loaded machine):
- The request is latched (reliable, transient-local, the last one kept) and the calls come one at a time
  (one detector thread per side), so the request waiting for its answer is always the one a detector that
  starts or restarts receives first: a detector that is not up yet, or dies holding it, leaves it waiting,
  not lost; the restarted one answers it.
- The answer is matched to its request by the stamp. An answer to an earlier request (a restarted detector
  answers the last request it finds, which may be one already answered) is ignored.
- A detector that cannot read the image answers so explicitly (`image_width` and `image_height` 0, no
  detections): the keyframe goes without detections at once (`refused`).
- Only a detector gone for good leaves a request unanswered. Under `orchard-map launch` that ends the graph
  (the supervisor restarts a dead detector up to 3 times, then stops the graph). Without the supervisor, a
  generous guard (`guard_s`, wall clock) keeps the side from waiting forever: the keyframe then goes without
  detections, the trunks near it are flagged `detector_unavailable_nearby`, and the miss is counted
  (`guard_expired`). Until a detector answers again, the next calls do not wait for one: a dead detector
  costs each later keyframe nothing, a restarted one is used as soon as it answers.
"""

from __future__ import annotations

import threading

import numpy as np
from orchard_mapping_msgs.msg import TrunkDetectionArray
from rclpy.node import Node
from sensor_msgs.msg import Image

from orchard_mapping.io.bags import header_ns
from orchard_mapping.ros.detections import detections_from_msg, is_refusal
from orchard_mapping.ros.messages import stamp_header
from orchard_mapping.ros.qos import LATCHED, REPLAY
from orchard_mapping.ros.trunk_detector import detections_topic, request_topic

__all__ = ["DETECTOR_GUARD_S", "RemoteDetector"]

# s: a guard against a detector gone for good (not a result's cut-off: an answer that comes before it is used,
# however late). Under the supervisor a detector that cannot be restarted ends the graph long before.
DETECTOR_GUARD_S = 600.0


class RemoteDetector:
    def __init__(self, node: Node, side: str, frame_id: str, guard_s: float = DETECTOR_GUARD_S) -> None:
        self.side, self.frame_id, self.guard_s = side, frame_id, guard_s
        self._pub = node.create_publisher(Image, request_topic(side), LATCHED)
        self._sub = node.create_subscription(TrunkDetectionArray, detections_topic(side), self._on_answer, REPLAY)
        self._cv = threading.Condition()
        self._waiting: int | None = None  # the stamp (ns) of the request waiting for its answer
        self._answer: TrunkDetectionArray | None = None
        self._gone = False  # the guard ran out: the detector is taken to be gone until it answers again
        self.unanswered = 0  # keyframes that went without detections (refused, or the guard ran out)
        self.refused = 0  # the detector could not read the image
        self.guard_expired = 0  # no answer within guard_s

    def _on_answer(self, msg: TrunkDetectionArray) -> None:
        with self._cv:
            self._gone = False  # a detector is there (this answer may be to an earlier request)
            if self._waiting is not None and header_ns(msg.header) == self._waiting:
                self._answer = msg
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
        with self._cv:
            self._waiting, self._answer = key, None
            self._pub.publish(img)
            # while the detector is taken to be gone, do not wait for one to come back (it is used once it answers)
            got = self._cv.wait_for(lambda: self._answer is not None, timeout=0.0 if self._gone else self.guard_s)
            msg, self._waiting, self._answer = self._answer, None, None
            if not got:
                self._gone = True
                self.guard_expired += 1
                self.unanswered += 1
                return None
        if is_refusal(msg):
            self.refused += 1
            self.unanswered += 1
            return None
        return detections_from_msg(msg)
