"""How every node process of the graph starts and stops (shared by the nodes' `main()`).

SIGINT and SIGTERM both end the spin the same way (the supervisor stops the graph with SIGTERM, a user
with Ctrl-C), so a node closes what it writes (a recorder's bag, a report) before it exits. Before the
process goes, every message it published must have been acknowledged by every reliable subscriber
(`wait_for_acks`): a latched result lives in its publisher, and a subscriber that had not received it yet (a
recorder behind a large side map on a loaded machine) would otherwise lose it. The wait ends on the
acknowledgements; `ACK_GUARD_S` only keeps a subscriber that is gone from holding the exit forever.
"""

from __future__ import annotations

import signal
import sys
import time
from collections.abc import Callable

import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from orchard_mapping.errors import OrchardMappingError

__all__ = ["ACK_GUARD_S", "StopNode", "run_node", "wait_for_acks"]

ACK_GUARD_S = 10.0  # s, a guard: at most this long at the exit for the acknowledgements (wait_for_acks)


class StopNode(Exception):
    """Raised from a node's callback when its work is done: the spin ends and the process exits with `code`
    (0: done; non-zero: done, but part of the work failed, which the supervisor then reports)."""

    def __init__(self, code: int = 0) -> None:
        super().__init__(code)
        self.code = code


def wait_for_acks(node: Node, guard_s: float = ACK_GUARD_S) -> bool:
    """Wait until every reliable subscriber acknowledged every message the node published (at most guard_s in
    all); False if one did not, or the context is already gone."""
    end = time.monotonic() + guard_s
    ok = True
    for pub in list(node.publishers):
        try:
            ok = pub.wait_for_all_acked(Duration(seconds=max(end - time.monotonic(), 0.0))) and ok
        except Exception:  # noqa: BLE001 - a context already shut down (Ctrl-C): nothing left to wait for
            return False
    return ok


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
            if node is not None and not wait_for_acks(node):
                print(f"{name}: not every subscriber acknowledged this node's last messages", file=sys.stderr)
            if node is not None:
                node.destroy_node()
            rclpy.try_shutdown()
    return code
