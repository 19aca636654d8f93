"""Restart policy: reload a node whose process died, with backoff and a limit.

A reload is an ordinary load of the same LoadNode request: it gets a new
unique_id (ids are never reused) and its own LOADED event. The delay starts
at ``initial_s`` and doubles with each death of the same node's lineage, up
to ``max_s``; a node that stayed up ``stable_s`` starts again from
``initial_s``. A lineage that died ``limit`` restarts in a row, none of them
up ``stable_s``, is not restarted again (as a service manager's start limit):
each crash leaves the dead process's objects in memory (isolated/host.py;
~2.7 MiB and ~9 fds a per-node crash, measured in bench/leaks.py), so a
node that dies at every start must not drain the container.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from collections.abc import Callable

    from composition_interfaces.srv import LoadNode
    from rclpy.node import Node
    from rclpy.timer import Timer

POLICIES = ("never", "on-crash")
DEFAULT_LIMIT = 5


@dataclass
class Lineage:
    name: str
    restarts: int = 0
    delay_s: float = 0.0
    in_a_row: int = 0  # restarts since it last stayed up stable_s


@dataclass(frozen=True)
class Decision:
    """What the policy does about one death: restart after ``delay_s``, or
    (``delay_s`` None) not again."""

    delay_s: float | None
    text: str  # for the CRASHED event and the log


class RestartPolicy:
    def __init__(
        self,
        node: Node,
        reload: Callable[[LoadNode.Request, Lineage], None],
        *,
        initial_s: float = 0.5,
        max_s: float = 30.0,
        stable_s: float = 60.0,
        limit: int = DEFAULT_LIMIT,
    ) -> None:
        if limit < 1:
            raise ValueError("a restart limit is at least 1")
        self._node = node
        self._reload = reload  # reload(request, lineage)
        self.initial_s, self.max_s, self.stable_s, self.limit = initial_s, max_s, stable_s, limit
        self._timers: list = []

    def on_crash(self, request: LoadNode.Request, lineage: Lineage, uptime_s: float) -> Decision:
        """Schedule a reload, unless the lineage reached the limit."""
        if uptime_s >= self.stable_s:
            lineage.in_a_row, lineage.delay_s = 0, 0.0
        if lineage.in_a_row >= self.limit:
            return Decision(
                None,
                f"not restarted again: it died {lineage.in_a_row + 1} times in a row, "
                f"each within {self.stable_s:g} s of its start (restart limit {self.limit})",
            )
        lineage.delay_s = self.initial_s if lineage.delay_s == 0 else min(self.max_s, lineage.delay_s * 2)
        lineage.restarts += 1
        lineage.in_a_row += 1
        delay = lineage.delay_s
        timer: Timer = None  # type: ignore[assignment]  # set below, before fire() can run

        def fire() -> None:
            timer.cancel()
            self._timers.remove(timer)
            self._node.destroy_timer(timer)
            self._reload(request, lineage)

        timer = self._node.create_timer(delay, fire)
        self._timers.append(timer)
        return Decision(
            delay,
            f"restarting in {delay:g} s (restart {lineage.restarts}, {lineage.in_a_row} of {self.limit} in a row)",
        )

    def cancel_all(self) -> None:
        for timer in self._timers:
            timer.cancel()
            self._node.destroy_timer(timer)
        self._timers.clear()


def uptime(start_time_ns: int) -> float:
    return (time.time_ns() - start_time_ns) / 1e9
