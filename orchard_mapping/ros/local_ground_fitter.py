"""`local_ground_fitter`: each side's trunk landmarks with their coarse axes and local grounds (paper: "Local
Ground Plane"), from the side's fused cloud and trunk detections, once the side is fused.

In:  `/orchard/<side>/side_geometry`  orchard_mapping_msgs/SideMap (latched) whose payload is the side's
     core.sidemap.SideGeometry (encoding orchard_mapping.side_geometry/1+npz: keyframe poses, fused cloud, the
     keyframes given to the detector with their depth and detections), from `rgbd_odometry`
Out: `/orchard/<side>/local_grounds`  orchard_mapping_msgs/LocalGroundArray (latched, the geometry's header):
     one LocalGround per trunk landmark (pipeline.trunks.fit_grounds, the first step of `orchard-map run`'s
     trunk modelling): its local ground, else the wide ground its diameter height is read from, else none;
     with the landmark's detections, points and coarse axis, which `rgbd_odometry` fits the trunk
     cylinders with (the second step). Every value is float64: the graph's trunks are `run`'s.
The grounds are fitted in the subscription callback: the node does nothing else meanwhile. A side geometry
already answered (a restart receives the latched one again) is answered again, with the same grounds.
"""

from __future__ import annotations

import sys
import time

from orchard_mapping_msgs.msg import LocalGroundArray, SideMap as SideMapMsg
from rclpy.node import Node

from orchard_mapping.errors import OrchardMappingError
from orchard_mapping.io.sidemap_codec import SIDE_GEOMETRY_ENCODING, SideMapFormatError, decode_side_geometry
from orchard_mapping.pipeline import SIDES
from orchard_mapping.pipeline.trunks import fit_grounds
from orchard_mapping.ros.messages import trunk_grounds_to_msg
from orchard_mapping.ros.params import ConfigParameters
from orchard_mapping.ros.qos import LATCHED
from orchard_mapping.ros.spin import run_node

__all__ = ["LocalGroundFitterNode", "geometry_topic", "grounds_topic", "main"]


def geometry_topic(side: str) -> str:
    return f"/orchard/{side}/side_geometry"


def grounds_topic(side: str) -> str:
    return f"/orchard/{side}/local_grounds"


class LocalGroundFitterNode(Node):
    def __init__(self) -> None:
        super().__init__("local_ground_fitter")
        self.params = ConfigParameters(self)
        self.answered = 0  # side geometries answered
        self.errors: list[str] = []
        self._pubs = {side: self.create_publisher(LocalGroundArray, grounds_topic(side), LATCHED) for side in SIDES}
        for side in SIDES:
            self.create_subscription(SideMapMsg, geometry_topic(side),
                                     lambda msg, side=side: self._on_geometry(side, msg), LATCHED)

    def _on_geometry(self, side: str, msg: SideMapMsg) -> None:
        stamp = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        where = f"{geometry_topic(side)} at {stamp:.3f} s"
        t0 = time.perf_counter()
        try:
            if msg.encoding != SIDE_GEOMETRY_ENCODING:
                raise SideMapFormatError(f"{where}: encoding {msg.encoding!r}, this node reads "
                                         f"{SIDE_GEOMETRY_ENCODING!r}")
            geometry = decode_side_geometry(msg.data.tobytes() if hasattr(msg.data, "tobytes") else bytes(msg.data),
                                            where)
            if geometry.side != side:
                raise SideMapFormatError(f"{where}: the payload is the {geometry.side} side's")
            grounds = fit_grounds(geometry, self.params.config)
        except OrchardMappingError as err:  # reported; the odometry node then fits the grounds itself
            self.errors.append(str(err))
            self.get_logger().error(f"no local grounds: {err}")
            return
        # the geometry's own header (frame odom_<side>, the side's last keyframe): how the odometry node pairs them
        out = trunk_grounds_to_msg(grounds, side, msg.header.frame_id, 0.0)
        out.header.stamp = msg.header.stamp
        for m in out.grounds:
            m.header = out.header
        self._pubs[side].publish(out)
        self.answered += 1
        kinds = [m.kind for m in out.grounds]
        self.get_logger().info(f"{side} side: {len(grounds)} trunk landmarks, {kinds.count('local')} local grounds, "
                               f"{kinds.count('wide')} wide, in {time.perf_counter() - t0:.2f} s")


def main(argv: list[str] | None = None) -> int:
    return run_node(LocalGroundFitterNode, "local_ground_fitter")


if __name__ == "__main__":
    sys.exit(main())
