"""The watchdog: if the container's executors stop making progress for
``timeout`` seconds, every Python thread's stack goes to stderr and the
container exits with status 1 (its children die with it, PR_SET_PDEATHSIG).

It is faulthandler's dump_traceback_later, re-armed once every watched
executor has shown progress since the last arming: the services' executor
through a timer on the container's node, the nodes' executor (thread mode's
nodes spin there) through a task the timer hands it. The dump runs on
faulthandler's own C thread and needs neither the GIL nor any lock, so it
still fires when a dead child has left the interpreter or an executor stuck.
The typical cause in isolated mode is a child that died holding a lock the
container then waits for; in thread mode, a callback that never returns.
"""
from __future__ import annotations

import faulthandler
import sys
import threading

BANNER = "cloneguard watchdog"


class Watchdog:
    def __init__(self, node, timeout_s: float, *, executors=(), on_tick=None):
        """``node`` spins on the executor whose timer drives the watchdog;
        ``executors`` are the others that must keep making progress."""
        if timeout_s <= 0:
            raise ValueError("watchdog timeout must be positive")
        self.timeout_s = timeout_s
        self._on_tick = on_tick
        self._log = node.get_logger()
        self._watched = list(executors)
        self._lock = threading.Lock()
        self._progressed: set[int] = set()     # indexes into _watched since the last arming
        self._pending: dict[int, object] = {}  # a task handed out, not yet run
        self._arm()
        self._timer = node.create_timer(min(1.0, timeout_s / 4), self._tick)
        self._log.info(
            f"{BANNER}: if an executor makes no progress for {timeout_s:g} s, "
            "the stacks of all threads are printed and the container exits with status 1"
        )

    def _arm(self) -> None:
        faulthandler.dump_traceback_later(self.timeout_s, repeat=False, file=sys.stderr, exit=True)

    def _tick(self) -> None:
        for index, executor in enumerate(self._watched):
            task = self._pending.get(index)
            if task is None or task.done():
                self._pending[index] = executor.create_task(self._progress, index)
        self._progress(None)
        if self._on_tick is not None:
            self._on_tick()

    def _progress(self, index: int | None) -> None:
        with self._lock:
            if index is not None:
                self._progressed.add(index)
            elif len(self._progressed) == len(self._watched):
                # The timer's executor is here, and every other one has run
                # a task since the last arming.
                self._progressed.clear()
                self._arm()

    def close(self) -> None:
        faulthandler.cancel_dump_traceback_later()
        self._timer.cancel()
