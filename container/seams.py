"""The one seam through which the test rig reaches into the container.

Fault injection needs four things inside the product: a LoadNode extra
argument that drops the node's LOADED event (a lost event), a call made
while an intra-process queue operation holds its lock (to die right there),
a progress-board write left half-done, and stop points: a node process that
stops itself, when asked, inside the allocator, inside CPython's object
allocator or holding a Python lock, so that a kill from outside lands there
(isolated/allocguard/stops.c; the harness asks with a sigqueue of the signal named by
``CLONEGUARD_STOP_SIGNAL`` in the container's environment; a Python lock
may be named, by ``stop_lock_key``). All are here,
and all are off unless the test rig is installed: the cloneguard-testrig distribution
declares itself in the entry-point group ``cloneguard.test_rig``. A
production install has no test rig, so nothing can switch them on; the
extra argument is then an unknown one, ignored as upstream ignores those.
"""

from __future__ import annotations

import functools
import os
import signal
import zlib
from collections.abc import Callable
from importlib.metadata import entry_points

RIG_GROUP = "cloneguard.test_rig"
#: Environment: the real-time signal node processes take stop requests on.
STOP_SIGNAL_ENV = "CLONEGUARD_STOP_SIGNAL"
#: LoadNode extra argument (bool): the node loads, its LOADED event is not sent.
DROP_LOADED_EVENT = "cloneguard.fault.drop_loaded_event"

# Called with the queue while a put holds its lock, after the slot was
# written and before it is published; and while a take holds it, after the
# messages were read and before the commit. Set only through arm().
queue_mid_put: Callable[[object], None] | None = None
queue_mid_take: Callable[[object], None] | None = None


@functools.cache
def enabled() -> bool:
    """Whether the test rig is installed beside the product."""
    return any(True for _ in entry_points(group=RIG_GROUP))


def require(what: str) -> None:
    if not enabled():
        raise RuntimeError(f"{what} is fault injection: it needs the test rig (cloneguard-testrig) installed")


def arm(name: str, hook: Callable[[object], None] | None) -> None:
    """Set (or, with None, clear) ``queue_mid_put`` or ``queue_mid_take``."""
    if name not in ("queue_mid_put", "queue_mid_take"):
        raise ValueError(f"no seam called {name!r}")
    if hook is not None:
        require(name)
    globals()[name] = hook


def stop_lock_key(name: str) -> int:
    """The key a python-lock stop request names one lock by: of its name as
    the container gives it (``pkg.mod.NAME``, ``pkg.mod.OBJ.attr``: locks.py),
    32 bits, never 0 (0 asks for any lock)."""
    return zlib.crc32(name.encode()) or 1


def stop_signal() -> int:
    """The signal node processes take stop requests on (``STOP_SIGNAL_ENV``),
    0 for none: not set, or no test rig installed (then it is ignored, like
    the extra argument). A value that is not a real-time signal number is
    refused (ValueError, saying what is allowed)."""
    raw = os.environ.get(STOP_SIGNAL_ENV, "")
    if not raw or not enabled():
        return 0
    low, high = int(signal.SIGRTMIN), int(signal.SIGRTMAX)
    try:
        sig = int(raw)
    except ValueError:
        sig = 0
    if not low <= sig <= high:
        raise ValueError(f"{STOP_SIGNAL_ENV}={raw!r}: the stop signal must be a real-time signal, {low} to {high}")
    return sig
