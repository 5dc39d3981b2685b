"""How every node process of the graph starts and stops (shared by the nodes' `main()`).

SIGINT and SIGTERM both end the spin the same way (the supervisor stops the graph with SIGTERM, a user
with Ctrl-C), so a node closes what it writes (a recorder's bag, a report) before it exits.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from orchard_mapping.errors import OrchardMappingError

__all__ = ["StopNode", "run_node"]


class StopNode(Exception):
    """Raised from a node's callback when its work is done: the spin ends and the process exits with `code`
    (0: done; non-zero: done, but part of the work failed, which the supervisor then reports)."""

    def __init__(self, code: int = 0) -> None:
        super().__init__(code)
        self.code = code


def run_node(make: Callable[[], Node], name: str, finish: Callable[[Node], None] | None = None) -> int:
    """rclpy.init, build the node, spin until SIGINT/SIGTERM (or the node shuts the context down), then
    finish(node) and shut down. A typed error while building or spinning is one line on stderr, exit 2."""
    rclpy.init()
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # SIGTERM stops like Ctrl-C
    node: Node | None = None
    code = 0
    try:
        node = make()
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except StopNode as stop:
        code = stop.code
    except OrchardMappingError as err:
        print(f"{name}: {err}", file=sys.stderr)
        code = 2
    finally:
        try:
            if node is not None and finish is not None:
                finish(node)
        finally:
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
    return code
