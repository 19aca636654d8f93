"""The node watchdog (``--node-watchdog SECONDS``, isolated mode): a node
whose callback has been running longer than SECONDS is aborted, alone.

The container's watchdog (``container/watchdog.py``) ends the whole container
when the container stops making progress: the right answer to a lock the
container needs and will never get. A node's callback that never returns is a
different fault: in isolated mode it stalls only that node's process, so only
that process need end. Each child stamps its slot on the progress board when a
callback starts and clears the stamp when it ends (``host.py``,
``board.py``); this reads the board from a timer of the container's own node
and has the host send SIGABRT to a node whose stamp is older than the limit.
The node's crash report (native and Python stacks: where it hung) goes to the
log, and it is reported CRASHED with the reason, as any crash, so
``--restart-policy on-crash`` loads it again.

An idle node runs no callback and is never aborted. A callback that keeps
the GIL (a C call that never returns without releasing it) stops this timer
with every other Python thread: only the container's watchdog, whose last
resort runs without the GIL, ends that.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rclpy.node import Node

    from .host import IsolatedHost


class NodeWatchdog:
    def __init__(self, node: Node, host: IsolatedHost, limit_s: float) -> None:
        if limit_s <= 0:
            raise ValueError("node watchdog limit must be positive")
        self.limit_s = limit_s
        self._host = host
        self._timer = node.create_timer(min(1.0, limit_s / 4), self._check)
        node.get_logger().info(
            f"node watchdog: a node whose callback runs longer than {limit_s:g} s is aborted "
            "(SIGABRT, with its stacks) and reported CRASHED"
        )

    def _check(self) -> None:
        now = time.monotonic_ns()
        for slot in self._host.board.snapshot():
            if slot.busy_ns and (now - slot.busy_ns) / 1e9 > self.limit_s:
                ran = (now - slot.busy_ns) / 1e9
                self._host.abort(
                    slot.unique_id,
                    f"its callback ran for {ran:.1f} s, longer than --node-watchdog {self.limit_s:g} s "
                    f"({slot.beats} callback(s) had run before it)",
                )

    def close(self) -> None:
        self._timer.cancel()
