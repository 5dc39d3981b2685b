"""The rosbags type store used for offline bag reading and writing.

ROS 2 Jazzy's standard messages plus our own `orchard_mapping_msgs/msg/*`,
registered from the `.msg` files shipped with the package, so neither the CLI
nor the tests need a ROS build to (de)serialize them.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from orchard_mapping.resources import msg_dir

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

__all__ = ["MSG_PACKAGE", "orchard_msgtypes", "typestore"]

MSG_PACKAGE = "orchard_mapping_msgs"


@functools.lru_cache(maxsize=1)
def _our_fielddefs() -> dict:
    """Field definitions of every `orchard_mapping_msgs/msg/*.msg`, keyed by full type name."""
    defs: dict = {}
    for path in sorted(msg_dir().glob("*.msg")):
        # Relative references such as `TrunkCylinder[]` resolve inside the same package.
        defs.update(get_types_from_msg(path.read_text(), f"{MSG_PACKAGE}/msg/{path.stem}"))
    return defs


def orchard_msgtypes() -> tuple[str, ...]:
    """Full names of our message types, e.g. `orchard_mapping_msgs/msg/TrunkCylinder`."""
    return tuple(sorted(_our_fielddefs()))


@functools.lru_cache(maxsize=1)
def typestore() -> Typestore:
    """ROS 2 Jazzy type store with our messages registered (cached; do not register more into it)."""
    store = get_typestore(Stores.ROS2_JAZZY)
    store.register(_our_fielddefs())
    return store
