"""Repairs after a node process's death, as data.

A process that dies holding one of the container's robust mutexes leaves
its state to the next locker, which repairs it (EOWNERDEAD): the progress
board (a half-written slot), an intra-process queue. A Python lock it held
is taken over by the next acquirer (locks.py), a pthread mutex released by
the monitor (isolated/clonecore/mutexes.c). The repairer may be a
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
PROGRESS_BOARD = "progress-board"  # a node's half-written progress-board slot
INTRA_QUEUE = "intra-queue"  # a subscription's intra-process queue
PYTHON_LOCK = "python-lock"  # a Python lock taken over from a dead holder (locks.py)
NATIVE_MUTEX = "native-mutex"  # a pthread mutex a dead node held, released (mutexes.c)

#: How every log line about a lock left as it was begins (a Python lock with
#: no holder known, a native lock the doctor cannot release): the harness's
#: hang diagnosis quotes these lines.
NOT_REPAIRED = "lock not repaired: "


@dataclass(frozen=True)
class RecordedRepair:
    state: str  # one of the values above
    unique_id: int  # the node whose state it was
    detail: str
    stamp_ns: int


_pending: collections.deque[RecordedRepair] = collections.deque()


def record(state: str, unique_id: int, detail: str) -> None:
    """From any task: one append (atomic under the GIL every task shares)."""
    _pending.append(RecordedRepair(state, unique_id, detail, time.time_ns()))


def drain() -> list[RecordedRepair]:
    """The container's thread takes what was recorded since the last call."""
    out = []
    while True:
        try:
            out.append(_pending.popleft())
        except IndexError:
            return out
