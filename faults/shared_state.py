"""State that nodes of one isolated container share, as any module's would:
the locks the lock faults die holding and their siblings wait for, and
where a heap victim's buffer is.

One interpreter serves every node process of an isolated container, so these
module globals are the same objects in each (faults/components.py:
DieHoldingPythonLock, WaitsForPythonLock).
"""

from __future__ import annotations

import ctypes
import logging
import threading

LOCK = threading.Lock()
RLOCK = threading.RLock()
# Its lock is the one Condition() makes itself: what a dead holder leaves is
# named by the container as CONDITION._lock (tests/test_stop_points.py).
CONDITION = threading.Condition()


class _Quiet(logging.Handler):
    """A handler that writes nothing: only its lock matters here."""

    def emit(self, record: logging.LogRecord) -> None:
        pass


HANDLER = _Quiet()
KINDS = ("lock", "rlock", "condition", "logging")


def lock_of(kind: str):
    """The lock object behind ``kind`` (a Condition's and a handler's own)."""
    lock = CONDITION._lock  # type: ignore[attr-defined]  # private, but the one a Condition waits on
    return {"lock": LOCK, "rlock": RLOCK, "condition": lock, "logging": HANDLER.lock}[kind]


def take(kind: str) -> None:
    """Hold the ``kind`` lock (as code that is inside it would)."""
    if kind == "lock":
        LOCK.acquire()
    elif kind == "rlock":
        RLOCK.acquire()
        RLOCK.acquire()  # twice: a recursion the dead holder leaves behind
    elif kind == "condition":
        CONDITION.acquire()
    elif kind == "logging":
        HANDLER.acquire()
    else:
        raise ValueError(f"kind must be one of {KINDS}, not {kind!r}")


# pylocks.c's lock object: PyObject_HEAD (16 bytes), then the lock word.
_LOCK_WORD_OFFSET = 16


def take_word_only(kind: str) -> None:
    """Take the ``kind`` lock's word as the first step of an acquire does,
    and stop there: its holder is not recorded (container/isolated/pylocks.c
    must be the lock type: an isolated container's)."""
    lock = lock_of(kind)
    if not type(lock).__module__.endswith("._pylocks"):
        raise RuntimeError("take_word_only needs the container's lock types (an isolated container)")
    word = ctypes.c_uint32.from_address(id(lock) + _LOCK_WORD_OFFSET)
    if word.value != 0:
        raise RuntimeError("the lock is held")
    word.value = 1


def use(kind: str) -> None:
    """What a sibling does with the ``kind`` lock, every time."""
    if kind == "lock":
        with LOCK:
            pass
    elif kind == "rlock":
        with RLOCK:
            pass
    elif kind == "condition":
        with CONDITION:
            CONDITION.wait(0.001)  # a waiter: it gives the lock up and takes it back
    elif kind == "logging":
        HANDLER.handle(logging.LogRecord("faults", logging.INFO, __file__, 0, "beat", None, None))
    else:
        raise ValueError(f"kind must be one of {KINDS}, not {kind!r}")


# node name -> (address, size) of the buffer a HeapVictim keeps in its own
# process (faults/components.py: HeapVictim, WildWriter).
HEAP_BUFFERS: dict[str, tuple[int, int]] = {}
# node name -> addresses of 64-byte blocks a HeapVictim malloc'd in its own
# heap for other nodes to free (faults/components.py: DoubleFreer,
# UseAfterFree).
DONATED_BLOCKS: dict[str, list[int]] = {}
# Garbage cycles CycleMakers leave for each other: each new one links to one
# another node made (faults/components.py: CycleMaker).
CYCLES: list = []
