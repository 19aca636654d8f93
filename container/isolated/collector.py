"""Garbage collection in isolated mode: only ever on a thread of the container.

Every node process runs Python in the container's one interpreter, and
CPython collects on whichever thread allocates past the threshold. A
collection keeps the generations in a state only its own end repairs
(interp.c): a node process killed in the middle of one left them torn, and
the container died at its next untrack. So while a CloneCore is open,
automatic collection is off, and the collector thread here collects
whenever CPython would have (``cg_gc_wait_due`` watches the counts without
the GIL), with CPython's own ``gc.collect(generation)``.

What the ``gc`` module says keeps its meaning, for the container's code and
a component's alike: ``gc.disable()``/``gc.enable()``/``gc.isenabled()``
switch these collections, and ``gc.collect()`` called in a node process is
run on the collector's thread, its caller waiting for the result. Only
``gc.freeze()`` and friends still run where they are called.
"""

from __future__ import annotations

import gc
import os
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing import Any

# How often the counts are looked at, off the GIL. CPython collects
# generation 0 every 700 allocations of tracked objects; a busy node makes
# that many in well under this, so a collection here finds more young
# objects than CPython's would (each takes a little longer, as many fewer).
INTERVAL_US = 2000


class Collector:
    def __init__(self, ffi: Any, lib: Any, after_collection: Callable[[], object] | None = None) -> None:
        """``after_collection``: run on the collector's thread, holding the
        GIL, after each collection (the core keeps pybind11's registry
        ahead there)."""
        self._lib, self._ffi = lib, ffi
        self._after_collection = after_collection
        self._wake = ffi.new("int *")
        self._pid = os.getpid()
        self._lock = threading.Lock()
        self._cond = threading.Condition(self._lock)
        self._asked: list[list] = []  # [generation, result or None]
        self._closing = False
        self._enabled = gc.isenabled()  # what gc.enable()/disable() say
        self._saved = (gc.enable, gc.disable, gc.isenabled, gc.collect)
        self._collect = gc.collect
        gc.disable()
        gc.enable, gc.disable, gc.isenabled, gc.collect = (
            self._enable,
            self._disable,
            self._isenabled,
            self._collect_for_caller,
        )
        self._thread = threading.Thread(target=self._run, name="cloneguard-gc", daemon=True)
        self._thread.start()

    # -- the gc module's calls, as a component sees them -----------------
    def _enable(self) -> None:
        self._enabled = True
        self._poke()

    def _disable(self) -> None:
        self._enabled = False

    def _isenabled(self) -> bool:
        return self._enabled

    def _collect_for_caller(self, generation: int = 2) -> int:
        if not isinstance(generation, int) or not 0 <= generation <= 2:
            return self._collect(generation)  # CPython's own error
        if os.getpid() == self._pid or threading.current_thread() is self._thread:
            return self._collect_here(generation)
        request = [generation, None]
        with self._cond:
            self._asked.append(request)
            self._poke()
            self._cond.notify_all()
            self._cond.wait_for(lambda: request[1] is not None or self._closing)
        return request[1] if request[1] is not None else 0

    # -- the collector's thread ------------------------------------------
    def _poke(self) -> None:
        self._wake[0] = 1

    def _run(self) -> None:
        while True:
            generation = self._lib.cg_gc_wait_due(INTERVAL_US, self._wake)  # off the GIL
            if generation >= 0:
                if self._enabled:
                    self._collect_here(generation)
                else:
                    self._sleep_while_disabled()
                continue
            self._wake[0] = 0
            with self._cond:
                asked, self._asked = self._asked, []
                if self._closing:
                    self._cond.notify_all()
                    return
            for request in asked:
                request[1] = self._collect_here(request[0])
            with self._cond:
                self._cond.notify_all()

    def _collect_here(self, generation: int) -> int:
        """gc.collect(generation), after what a death with the GIL left is
        put out of the collector's sight (interp.c), in one hold of the GIL."""
        found = self._lib.cg_gc_collect(self._ffi.cast("void *", id(self._collect)), generation)
        if self._after_collection is not None:
            self._after_collection()
        return found

    def _sleep_while_disabled(self) -> None:
        with self._cond:
            self._cond.wait_for(lambda: self._enabled or self._asked or self._closing, 0.1)

    def close(self) -> None:
        """Stop the thread; automatic collection as it was before."""
        with self._cond:
            self._closing = True
            self._poke()
            self._cond.notify_all()
        self._thread.join()
        gc.enable, gc.disable, gc.isenabled, gc.collect = self._saved
        if self._enabled:
            gc.enable()
