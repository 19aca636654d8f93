"""Restart policy: reload a node whose process died, with backoff.

A reload is an ordinary load of the same LoadNode request: it gets a new
unique_id (ids are never reused) and its own LOADED event. The delay starts
at ``initial_s`` and doubles with each death of the same node's lineage, up
to ``max_s``; a node that stayed up ``stable_s`` starts again from
``initial_s``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

POLICIES = ("never", "on-crash")


@dataclass
class Lineage:
    name: str
    restarts: int = 0
    delay_s: float = 0.0


class RestartPolicy:
    def __init__(self, node, reload, *, initial_s: float = 0.5, max_s: float = 30.0, stable_s: float = 60.0):
        self._node = node
        self._reload = reload            # reload(request, lineage) -> new unique_id or None
        self.initial_s, self.max_s, self.stable_s = initial_s, max_s, stable_s
        self._timers = []

    def on_crash(self, request, lineage: Lineage, uptime_s: float) -> float:
        """Schedule a reload; returns the delay."""
        if uptime_s >= self.stable_s or lineage.delay_s == 0:
            lineage.delay_s = self.initial_s
        else:
            lineage.delay_s = min(self.max_s, lineage.delay_s * 2)
        lineage.restarts += 1
        delay = lineage.delay_s
        timer = None

        def fire():
            timer.cancel()
            self._timers.remove(timer)
            self._node.destroy_timer(timer)
            self._reload(request, lineage)

        timer = self._node.create_timer(delay, fire)
        self._timers.append(timer)
        return delay

    def cancel_all(self) -> None:
        for timer in self._timers:
            timer.cancel()
            self._node.destroy_timer(timer)
        self._timers.clear()


def uptime(start_time_ns: int) -> float:
    return (time.time_ns() - start_time_ns) / 1e9
