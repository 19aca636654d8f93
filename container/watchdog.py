"""The watchdog: if the container's executors stop making progress for
``timeout`` seconds, every Python thread's stack goes to stderr and the
container exits with status 1 (its children die with it, PR_SET_PDEATHSIG).

Progress: the watchdog is re-armed once every watched executor has shown
progress since the last arming: the services' executor through a timer on
the container's node, the nodes' executor (thread mode's nodes spin there)
through a task the timer hands it.

The dump has two stages, because the two ways to take it fail differently:
- At ``timeout``, a Python thread of the watchdog dumps every thread's stack
  while it holds the GIL, so no other thread's frames change under the dump.
- If that thread cannot run (the GIL itself is stuck: a dead child left the
  interpreter, or a C call holds it), a C thread dumps ``FALLBACK_GRACE_S``
  later without the GIL and without any lock, and exits: faulthandler's in
  thread mode, the clone core's in isolated mode (``Clock``). That dump reads
  the frames of threads that may be running, so it is only the last resort:
  taken while Python threads still run, it can read a frame being freed and
  crash the container with SIGSEGV instead of exiting 1.

Time is read on a ``Clock``. In isolated mode it stands still while a core
dump is asked for or written (--core-dumps): a node that crashed holding
the GIL keeps it until its dump is written, seconds in which no Python runs
and which are no hang (so a hang of another kind that overlaps a dump is
found that much later).
The typical cause in isolated mode is a child that died holding a lock the
container then waits for; in thread mode, a callback that never returns.

The container's shutdown has a bound of its own (``bound_shutdown``): the
same two-stage dump and exit if stopping takes longer than it, since from
then on no executor is watched (a node that never stops, a DDS call that
never returns, would otherwise keep the container alive until someone kills
it, and say nothing of where it is stuck).
"""

from __future__ import annotations

import faulthandler
import os
import sys
import threading
import time
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from rclpy.executors import Executor
    from rclpy.node import Node

BANNER = "cloneguard watchdog"
FALLBACK_GRACE_S = 2.0


class Clock(Protocol):
    """What a deadline's time is read on, with its last resort: a C thread
    that, unless armed again first, prints every thread's stack (after the
    banner it was made with) and ends the container with status 1."""

    def now(self) -> float: ...

    def arm_last_resort(self, after_s: float) -> None: ...

    def close(self) -> None: ...


class MonotonicClock:
    """Thread mode's: CLOCK_MONOTONIC, and faulthandler's C thread (which
    prints its own banner, ``Timeout (h:mm:ss)!``)."""

    def __init__(self, banner: str):
        pass

    def now(self) -> float:
        return time.monotonic()

    def arm_last_resort(self, after_s: float) -> None:
        faulthandler.dump_traceback_later(after_s, repeat=False, file=sys.stderr, exit=True)

    def close(self) -> None:
        faulthandler.cancel_dump_traceback_later()


ClockFactory = Callable[[str], Clock]  # from the last resort's banner


class _Deadline:
    """The two-stage dump and exit at a deadline that ``arm`` moves."""

    def __init__(self, timeout_s: float, what: str, clock: ClockFactory):
        self.timeout_s = timeout_s
        self._what = what  # "<what> for <timeout> s" is the reason printed
        self._clock = clock(
            f"{BANNER}: {what} for {timeout_s + FALLBACK_GRACE_S:g} s and no Python thread could run since; "
            "the stacks of all threads follow and the container exits with status 1\n"
        )
        self._deadline = 0.0
        self._closed = threading.Event()
        self.arm()
        self._thread = threading.Thread(target=self._watch, name="cloneguard-watchdog", daemon=True)
        self._thread.start()

    def arm(self) -> None:
        self._deadline = self._clock.now() + self.timeout_s
        self._clock.arm_last_resort(self.timeout_s + FALLBACK_GRACE_S)

    def _watch(self) -> None:
        while True:
            remaining = self._deadline - self._clock.now()
            if remaining <= 0:
                break
            if self._closed.wait(remaining):
                return
        # Holding the GIL from here on: no thread runs Python code while the
        # dump reads the frames, and nothing re-arms us.
        sys.stderr.write(
            f"{BANNER}: {self._what} for {self.timeout_s:g} s; the stacks of all threads follow "
            "and the container exits with status 1\n"
        )
        sys.stderr.flush()
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        sys.stderr.flush()
        os._exit(1)

    def close(self) -> None:
        self._closed.set()
        self._clock.close()
        self._thread.join()


def bound_shutdown(timeout_s: float, clock: ClockFactory = MonotonicClock) -> _Deadline:
    """From now on, the container exits with every thread's stack if it is
    still stopping ``timeout_s`` seconds later. ``close()`` once stopped."""
    return _Deadline(timeout_s, "still stopping", clock)


class Watchdog:
    def __init__(
        self,
        node: Node,
        timeout_s: float,
        *,
        executors: Iterable[Executor] = (),
        on_tick: Callable[[], object] | None = None,
        clock: ClockFactory = MonotonicClock,
    ) -> None:
        """``node`` spins on the executor whose timer drives the watchdog;
        ``executors`` are the others that must keep making progress."""
        if timeout_s <= 0:
            raise ValueError("watchdog timeout must be positive")
        self.timeout_s = timeout_s
        self._on_tick = on_tick
        self._log = node.get_logger()
        self._watched = list(executors)
        self._lock = threading.Lock()
        self._progressed: set[int] = set()  # indexes into _watched since the last arming
        self._pending: dict[int, Any] = {}  # a task handed out, not yet run
        self._deadline = _Deadline(timeout_s, "no progress", clock)
        self._timer = node.create_timer(min(1.0, timeout_s / 4), self._tick)
        self._log.info(
            f"{BANNER}: if an executor makes no progress for {timeout_s:g} s, "
            "the stacks of all threads are printed and the container exits with status 1"
        )

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
                self._deadline.arm()

    def close(self) -> None:
        self._deadline.close()
        self._timer.cancel()
