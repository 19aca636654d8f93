"""The watchdog: if the container's own executor stops making progress for
``timeout`` seconds, every Python thread's stack goes to stderr and the
container exits with status 1 (its children die with it, PR_SET_PDEATHSIG).

It is faulthandler's dump_traceback_later, re-armed from a timer on the
container's executor: the dump runs on faulthandler's own C thread and needs
neither the GIL nor any lock, so it still fires when a dead child has left
the interpreter or the executor stuck. The typical cause in isolated mode is
a child that died holding a lock the container then waits for.
"""
from __future__ import annotations

import contextlib
import faulthandler
import sys

BANNER = "cloneguard watchdog"


class Watchdog:
    def __init__(self, node, timeout_s: float, *, on_tick=None):
        if timeout_s <= 0:
            raise ValueError("watchdog timeout must be positive")
        self.timeout_s = timeout_s
        self._on_tick = on_tick
        self._log = node.get_logger()
        self._arm()
        self._timer = node.create_timer(min(1.0, timeout_s / 4), self._tick)
        self._log.info(
            f"{BANNER}: if this executor makes no progress for {timeout_s:g} s, "
            "the stacks of all threads are printed and the container exits with status 1"
        )

    def _arm(self, timeout_s: float | None = None) -> None:
        faulthandler.dump_traceback_later(timeout_s or self.timeout_s, repeat=False, file=sys.stderr, exit=True)

    @contextlib.contextmanager
    def allow(self, seconds: float):
        """A callback that may legitimately block the executor for up to
        ``seconds`` (a LoadNode waiting for a slow constructor)."""
        self._arm(seconds + self.timeout_s)
        try:
            yield
        finally:
            self._arm()

    def _tick(self) -> None:
        self._arm()
        if self._on_tick is not None:
            self._on_tick()

    def close(self) -> None:
        faulthandler.cancel_dump_traceback_later()
        self._timer.cancel()
