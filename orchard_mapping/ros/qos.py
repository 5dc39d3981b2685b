"""The QoS profiles of the node graph.

- Camera input: the sensor-data profile (best effort, volatile) with a deeper queue: a late or lost image
  is not worth a stalled driver, but the node's executor may wait a while for the GIL while a side is
  finished in a worker thread: with the profile's queue of 5, 46 of 486 colour images of the 2-tree
  fixture row were lost at 1x (test/ros/test_odometry_node.py); 60 (4 s at 15 Hz) holds such waits. Over loopback with the project's Fast DDS profile (a larger shared-memory
  segment, config/fastdds_large_messages.xml) no image is lost at 1x; the odometry node counts what it
  receives against the stamps it sees, so a loss is reported, never silent.
- Camera input from the project's own bag player (`orchard-map launch --bag`): reliable, same queue. The
  player publishes reliably; a best-effort reader still lost 5 of 316 images of the 2-tree drive bag at
  1x in one CI run of three on 2 cores (test/ros/test_odometry_node.py), while a side was being
  finished beside the tracking. A replay has no driver to stall, so nothing is lost. A live camera
  driver publishes best effort, which a reliable reader would not match: live input stays best effort.
- Results (side maps, clouds, cylinders, grounds, merges, traits, the side being recorded): reliable and
  transient-local with the last one kept, so a late subscriber (RViz, Foxglove, a recorder) gets it.
- Replay: the bag player publishes reliably (a reliable publisher serves best-effort and reliable
  subscribers alike), with a queue deep enough for a burst of stored messages.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

__all__ = ["CAMERA", "CAMERA_REPLAYED", "LATCHED", "REPLAY"]

CAMERA = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=60, reliability=qos_profile_sensor_data.reliability,
                    durability=qos_profile_sensor_data.durability)
CAMERA_REPLAYED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=60, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.VOLATILE)
LATCHED = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
REPLAY = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.VOLATILE)
