"""Stop points: a node's process asked to stop itself at a kind of place in
its own code, so that a kill from outside lands exactly there and not at
whatever instant a signal happens to arrive.

    at = stop_at(pid, "allocation")   # stopped (SIGSTOP) inside malloc, or HarnessTimeout
    os.kill(pid, signal.SIGKILL)       # dies there
    # or: signal_there(pid, signal.SIGSEGV), a fault it takes right there

The places (``PLACES``):

- ``allocation``: inside the allocator guard's malloc (the container counts
  the process as inside the allocator: a death there quarantines its heap);
- ``python-allocation``: inside CPython's object allocator, a block taken and
  its pool's count not yet updated, the GIL held;
- ``python-lock``: a Python lock (``threading.Lock``/``RLock``, the
  executor's own) just acquired, with the GIL; or one lock named, its
  key (the container's seams.stop_lock_key) in the request's high bits.

How: the harness starts every container with ``CLONEGUARD_STOP_SIGNAL`` in
its environment (``STOP_SIGNAL``, a real-time signal); a node process of an
isolated container with the allocator guard (the default) and the test rig
installed takes requests on it (the container's seams.py, isolated/allocguard/stops.c).
A request is a sigqueue of that signal whose value names the place and how
many passes to let go by first. Where the container does not take requests
(thread mode, ``--no-alloc-guard``, a container of another make) nothing
stops and ``stop_at`` says so when its time runs out.
"""

from __future__ import annotations

import ctypes
import os
import signal
import time
import zlib

from . import procfs
from .errors import HarnessTimeout

#: The signal the harness asks on, told to containers by STOP_SIGNAL_ENV.
STOP_SIGNAL = int(signal.SIGRTMAX) - 3
STOP_SIGNAL_ENV = "CLONEGUARD_STOP_SIGNAL"
#: place -> its number in a request (CGA_STOP_*, container/isolated/allocguard/allocguard.h;
#: tests/test_stop_points.py checks they agree)
PLACES = {"allocation": 1, "python-allocation": 2, "python-lock": 3}
_PLACE_BITS = 4  # CGA_STOP_REQUEST(place, n) = place | n << 4
MAX_PASSES = (1 << (31 - _PLACE_BITS)) - 1
_KEY_SHIFT = 32  # CGA_STOP_KEY_SHIFT: a named lock's key above the request


def lock_key(name: str) -> int:
    """The key a request names a lock by: the container's
    seams.stop_lock_key (tests/test_stop_points.py checks they agree; the
    harness never imports the container)."""
    return zlib.crc32(name.encode()) or 1


_libc = ctypes.CDLL(None, use_errno=True)
_libc.sigqueue.argtypes = (ctypes.c_int, ctypes.c_int, ctypes.c_void_p)


def _request(pid: int, value: int) -> None:
    if _libc.sigqueue(pid, STOP_SIGNAL, ctypes.c_void_p(value)) != 0:
        err = ctypes.get_errno()
        raise ProcessLookupError(err, f"cannot ask process {pid} to stop: {os.strerror(err)}")


_SYS_TGKILL = 234  # x86_64, the only platform an isolated container runs on


def signal_there(pid: int, sig: int) -> None:
    """Send ``sig`` to the stopped process's main task, the one that stopped
    at the place (a signal to the process could be taken by any of its
    threads), and let it go: it takes the signal right there."""
    if _libc.syscall(_SYS_TGKILL, pid, pid, int(sig)) != 0:
        err = ctypes.get_errno()
        raise ProcessLookupError(err, f"cannot signal process {pid}: {os.strerror(err)}")
    os.kill(pid, signal.SIGCONT)


def is_stopped(pid: int) -> bool:
    """Whether process ``pid`` is in a stop (its state is T)."""
    st = procfs.stat(pid)
    return st is not None and st.state == "T"


def stop_at(pid: int, place: str, *, after: int = 1, timeout: float = 5.0, lock: str = "") -> int:
    """Ask node process ``pid`` to stop at its ``after``-th pass of ``place``
    from now, and wait until it has; when (monotonic ns) it was seen
    stopped. With ``place`` python-lock, ``lock`` may name the one Python
    lock whose acquires count, as the container names locks (a module's
    global ``pkg.mod.NAME`` or an attribute of one ``pkg.mod.OBJ.attr``, as
    in its REPAIRED events). The caller ends it (SIGKILL) or lets it go
    (SIGCONT). HarnessTimeout if it did not get there within ``timeout``
    (the request is taken back first); ProcessLookupError if there is no
    such process."""
    if place not in PLACES:
        raise ValueError(f"no stop point {place!r}: the places are {', '.join(PLACES)}")
    if not 1 <= after <= MAX_PASSES:
        raise ValueError(f"after is 1 to {MAX_PASSES} passes, not {after!r}")
    if lock and place != "python-lock":
        raise ValueError(f"a lock is named only at python-lock, not at {place}")
    if is_stopped(pid):
        raise RuntimeError(f"process {pid} is stopped already (frozen?): it cannot pass {place}")
    key = lock_key(lock) if lock else 0
    _request(pid, PLACES[place] | after << _PLACE_BITS | key << _KEY_SHIFT)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if is_stopped(pid):
            return time.monotonic_ns()
        time.sleep(0.001)
    _request(pid, 0)  # taken back
    if is_stopped(pid):  # got there as it was taken back
        return time.monotonic_ns()
    where = f"{place} ({lock})" if lock else place
    raise HarnessTimeout(
        f"process {pid} did not stop at {where} within {timeout:g} s: it passed no such place "
        f"{after} time(s), or its container takes no stop requests (only an isolated container with the "
        "allocator guard, the default, and the test rig installed does)"
    )
