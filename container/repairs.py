"""Repairs of container-owned state, as data.

A process that dies holding one of the container's robust mutexes leaves
its state to the next locker, which repairs it (EOWNERDEAD): the progress
board (a half-written slot), an intra-process queue. That locker may be a
node process, which must not publish on the container's participant, so a
repair is only recorded here (one append, in container memory) and the
container's own thread publishes it as a ComponentEvent REPAIRED
(manager.py), which is how anyone outside learns of it.
"""
from __future__ import annotations

import collections
import time
from dataclasses import dataclass

#: ComponentEvent.repaired_state values
PROGRESS_BOARD = "progress-board"
INTRA_QUEUE = "intra-queue"


@dataclass(frozen=True)
class Repair:
    state: str            # PROGRESS_BOARD or INTRA_QUEUE
    unique_id: int        # the node whose state it was
    detail: str
    stamp_ns: int


_pending: collections.deque[Repair] = collections.deque()


def record(state: str, unique_id: int, detail: str) -> None:
    """From any task: one append (atomic under the GIL every task shares)."""
    _pending.append(Repair(state, unique_id, detail, time.time_ns()))


def drain() -> list[Repair]:
    """The container's thread takes what was recorded since the last call."""
    out = []
    while True:
        try:
            out.append(_pending.popleft())
        except IndexError:
            return out
