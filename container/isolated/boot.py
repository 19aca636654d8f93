"""``python -m cloneguard.container.isolated.boot SCRIPT ARG...``: an isolated
container's first Python code, then its script.

Python's lock types are replaced (pylocks.c: locks that know their
holder's process, container/locks.py says what for) before anything else is
imported: ``threading`` copies ``_thread.allocate_lock`` and
``_thread.RLock`` when it is first imported, and every lock made from then
on (threading, queue, logging, importlib's module locks) is then one of
these. The container re-executes itself through here (allocator.py).
"""

from __future__ import annotations

import _thread
import runpy
import sys


def install() -> None:
    if "threading" in sys.modules:
        raise RuntimeError("too late: threading is imported already, and has CPython's lock types")
    import cloneguard.container.isolated._pylocks as _pylocks  # an extension module

    _thread.allocate_lock = _thread.allocate = _pylocks.allocate_lock
    _thread.LockType = _pylocks.LockType  # type: ignore[misc]
    _thread.RLock = _pylocks.RLock  # type: ignore[misc]


if __name__ == "__main__":
    install()
    script, sys.argv = sys.argv[1], sys.argv[1:]
    runpy.run_path(script, run_name="__main__")
