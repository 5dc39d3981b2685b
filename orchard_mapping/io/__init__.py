"""Reading and writing files: bags (rosbags), the result folder (contract in docs/results.md)."""

from orchard_mapping.io.bag_writer import BagWriter, msg_header
from orchard_mapping.io.bags import BagSummary, RGBDSequence, describe_bag, iter_messages, read_rgbd
from orchard_mapping.io.typesys import orchard_msgtypes, typestore

__all__ = [
    "BagSummary",
    "BagWriter",
    "RGBDSequence",
    "describe_bag",
    "iter_messages",
    "msg_header",
    "orchard_msgtypes",
    "read_rgbd",
    "typestore",
]
