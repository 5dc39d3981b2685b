"""TF for RViz and Foxglove: `/tf` (the camera in each side's odom frame, every frame placed) and
`/tf_static` (each side's odom frame in `map` once the sides are merged).

tf2_ros is not on PyPI; only its message is needed: `tf2_msgs/msg/TFMessage`, which `make setup` builds
into the venv from `vendor/tf2_msgs` (the same definition as ROS 2 Jazzy's, so the same type hash). The
QoS are tf2_ros's own: `/tf` reliable and volatile with a deep queue, `/tf_static` reliable and
transient-local, every static transform a node has sent republished in one message, since a late
subscriber gets only the last message.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from orchard_mapping.core.geometry import matrix_to_quat, quat_to_matrix
from orchard_mapping.ros.messages import stamp_header

__all__ = ["TF_STATIC_TOPIC", "TF_TOPIC", "StaticTransforms", "Transforms", "transform_msg", "transform_of"]

TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"
TF_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=100, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
TF_STATIC_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.TRANSIENT_LOCAL)


def transform_msg(T_parent_child: np.ndarray, parent: str, child: str, stamp: float) -> TransformStamped:
    """A rigid 4x4 transform (child frame's points into the parent frame, metres) as a TransformStamped."""
    T = np.asarray(T_parent_child, float)
    msg = TransformStamped()
    stamp_header(msg.header, stamp, parent)
    msg.child_frame_id = child
    tr = msg.transform.translation
    tr.x, tr.y, tr.z = (float(v) for v in T[:3, 3])
    q = matrix_to_quat(T[:3, :3])  # x y z w
    rot = msg.transform.rotation
    rot.x, rot.y, rot.z, rot.w = (float(v) for v in q)
    return msg


def transform_of(msg: TransformStamped) -> np.ndarray:
    """(4, 4) T_parent_child of a TransformStamped (rclpy's or a decoded bag message)."""
    r, t = msg.transform.rotation, msg.transform.translation
    T = np.eye(4)
    T[:3, :3] = quat_to_matrix(np.array([r.x, r.y, r.z, r.w]))
    T[:3, 3] = (t.x, t.y, t.z)
    return T


class Transforms:
    """Publishes transforms that change (a `/tf` broadcaster)."""

    def __init__(self, node: Node) -> None:
        self._pub = node.create_publisher(TFMessage, TF_TOPIC, TF_QOS)

    def send(self, *transforms: TransformStamped) -> None:
        self._pub.publish(TFMessage(transforms=list(transforms)))


class StaticTransforms:
    """Publishes transforms that hold until replaced (a `/tf_static` broadcaster): each send republishes
    every child frame's latest transform, so one late message carries them all."""

    def __init__(self, node: Node) -> None:
        self._pub = node.create_publisher(TFMessage, TF_STATIC_TOPIC, TF_STATIC_QOS)
        self._by_child: dict[str, TransformStamped] = {}

    def send(self, *transforms: TransformStamped) -> None:
        for t in transforms:
            self._by_child[t.child_frame_id] = t
        self._pub.publish(TFMessage(transforms=list(self._by_child.values())))
