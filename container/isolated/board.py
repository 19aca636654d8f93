"""The progress board: per-node progress counters that children write and
the container reads, in container memory behind one robust mutex.

Each child, after every callback its executor runs, takes the board's lock
and updates its own slot (the count of callbacks run); before each callback
it stamps the slot's ``busy_ns``. The container reads the board from its watchdog tick
(which finds a lock a dead child left on it) and from the node watchdog
(``node_watchdog.py``: a callback running too long). It is the state a child can be holding a container lock
over when it dies, so it is built to be repaired:

* every slot update is bracketed by a sequence number made odd before the
  writes and even after, so a slot left half-written by a writer that died
  has an odd number;
* the lock is a robust mutex: the next locker after such a death is told
  (EOWNERDEAD), and :meth:`_repair` makes every odd slot even again (its
  counters are a lower bound, which is all a progress counter promises),
  then the mutex is marked consistent and everyone goes on.
"""

from __future__ import annotations

import ctypes
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

from .. import seams
from ..robust import RobustMutex

if TYPE_CHECKING:
    from collections.abc import Callable

SLOTS = 256


class _Slot(ctypes.Structure):
    _fields_ = [
        ("seq", ctypes.c_uint64),  # odd while being written
        ("unique_id", ctypes.c_uint64),
        ("pid", ctypes.c_int32),
        ("beats", ctypes.c_uint64),  # callbacks run so far
        ("busy_ns", ctypes.c_int64),  # CLOCK_MONOTONIC the running callback
        # started at; 0 between callbacks
    ]


@dataclass(frozen=True)
class SlotView:
    unique_id: int
    pid: int
    beats: int
    busy_ns: int  # when its running callback started; 0: none runs


@dataclass(frozen=True)
class BoardRepair:
    torn_slots: tuple[int, ...]  # unique_ids whose slot was half-written
    at_ns: int


_current: ProgressBoard | None = None


def current() -> ProgressBoard | None:
    """The board of this container process (None outside isolated mode)."""
    return _current


class ProgressBoard:
    def __init__(self, on_repair: Callable[[BoardRepair], None] | None = None) -> None:
        global _current
        self._slots = (_Slot * SLOTS)()
        self._free = list(range(SLOTS - 1, -1, -1))
        self._index: dict[int, int] = {}  # unique_id -> slot (container side)
        self._alloc_lock = threading.Lock()  # slot allocation: container threads only
        self.mutex = RobustMutex(repair=self._repair)
        self.repairs: list[BoardRepair] = []
        self._on_repair = on_repair
        _current = self

    # -- container side -----------------------------------------------------------

    def register(self, unique_id: int) -> int:
        with self._alloc_lock:
            if not self._free:
                raise RuntimeError(f"progress board full ({SLOTS} nodes)")
            slot = self._free.pop()
            self._index[unique_id] = slot
        with self.mutex:
            s = self._slots[slot]
            s.seq, s.unique_id, s.pid, s.beats, s.busy_ns = 0, unique_id, 0, 0, 0
        return slot

    def set_pid(self, slot: int, pid: int) -> None:
        with self.mutex:
            self._slots[slot].pid = pid

    def unregister(self, unique_id: int) -> None:
        with self._alloc_lock:
            slot = self._index.pop(unique_id, None)
            if slot is None:
                return
        with self.mutex:
            self._slots[slot].unique_id = 0
        with self._alloc_lock:
            self._free.append(slot)

    def snapshot(self) -> list[SlotView]:
        with self.mutex:
            return [SlotView(s.unique_id, s.pid, s.beats, s.busy_ns) for s in self._slots if s.unique_id]

    # -- child side ---------------------------------------------------------------

    def busy(self, slot: int) -> None:
        """A callback of ``slot``'s node starts (called in the node's child).
        One aligned 8-byte store, whole to any reader: no lock, so that a
        callback never waits for the board to start."""
        self._slots[slot].busy_ns = time.monotonic_ns()

    def beat(self, slot: int) -> None:
        """Record one finished callback for ``slot`` (called in the node's
        child)."""
        with self.mutex:
            s = self._slots[slot]
            s.seq += 1
            s.beats += 1
            s.busy_ns = 0
            s.seq += 1

    def begin_torn_write(self, slot: int) -> None:
        """Lock and start a slot update without finishing it: what a writer
        that dies half-way leaves. For fault injection only: the caller is
        expected to die holding the lock."""
        seams.require("a torn progress-board write")
        self.mutex.lock()
        self._slots[slot].seq += 1

    def slot_of_pid(self, pid: int) -> int | None:
        """The slot a process writes (for code running inside a child)."""
        with self.mutex:
            for i, s in enumerate(self._slots):
                if s.unique_id and s.pid == pid:
                    return i
        return None

    # -- repair (runs with the mutex held, after EOWNERDEAD) -------------------------

    def _repair(self) -> None:
        torn = []
        for s in self._slots:
            if s.seq % 2:
                s.seq += 1
                torn.append(s.unique_id)
        repair = BoardRepair(tuple(torn), time.monotonic_ns())
        self.repairs.append(repair)
        if self._on_repair is not None:
            self._on_repair(repair)
