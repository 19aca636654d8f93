"""One intra-process subscription's queue: a bounded ring behind a robust mutex.

Publishers (in their own processes) put message objects in, the
subscription's executor takes them out. The ring lives in the container's
memory, so any child can die in the middle of a put or a take; the design
makes that harmless instead of repairing it after the fact:

* The queue's visible state is one tuple, ``(head, count)``, replaced by a
  single attribute store. A slot outside ``[head, head + count)`` is
  invisible, so a writer fills a slot first and *then* publishes it by
  storing the new tuple: whatever instant a child dies at, the state is
  either the old tuple or the new one, never half of each.
* Dropping the oldest message when the ring is full is its own commit (the
  tuple shrinks first), so a slot that is visible is never overwritten.
* The lock is a robust mutex, so the next locker after a death gets
  EOWNERDEAD instead of hanging; the repair then only has to clear slot
  references outside the visible range (what the dead writer may have left,
  holding a message alive) and count itself.

A message object is handed over by reference: nothing is copied.
"""

from __future__ import annotations

from collections.abc import Callable

from cloneguard.container import seams
from cloneguard.container.robust import RobustMutex


class MessageQueue:
    """Bounded FIFO of message objects; the oldest is dropped when full."""

    def __init__(self, capacity: int, *, on_repair: Callable[[MessageQueue], None] | None = None):
        if capacity < 1:
            raise ValueError(f"queue capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self._slots: list[object] = [None] * capacity
        self._state = (0, 0)  # (head, count): the only commit point
        self.dropped = 0  # messages pushed out by newer ones (KEEP_LAST)
        self.repairs = 0  # times a locker found the previous owner dead
        self._on_repair = on_repair
        self._mutex = RobustMutex(self._repair)

    def __len__(self) -> int:
        return self._state[1]

    def put(self, message: object) -> bool:
        """Append ``message``; True if the queue was empty (the subscriber
        needs waking), False if it already had something to take."""
        with self._mutex:
            head, count = self._state
            if count == self.capacity:  # KEEP_LAST: the oldest goes
                head, count = (head + 1) % self.capacity, count - 1
                self._state = (head, count)  # commit the drop first
                self.dropped += 1
            self._slots[(head + count) % self.capacity] = message
            if seams.queue_mid_put is not None:  # fault injection (seams.py)
                seams.queue_mid_put(self)
            self._state = (head, count + 1)  # commit: now it is visible
            return count == 0

    def take_all(self) -> list[object]:
        """Remove and return everything queued, oldest first."""
        with self._mutex:
            head, count = self._state
            taken = [self._slots[(head + i) % self.capacity] for i in range(count)]
            if seams.queue_mid_take is not None:
                seams.queue_mid_take(self)
            self._state = ((head + count) % self.capacity, 0)  # commit
            for i in range(count):
                self._slots[(head + i) % self.capacity] = None
            return taken

    def _repair(self) -> None:
        """EOWNERDEAD: the committed state is consistent by construction;
        drop the references a dead owner left outside it."""
        head, count = self._state
        visible = {(head + i) % self.capacity for i in range(count)}
        for i in range(self.capacity):
            if i not in visible:
                self._slots[i] = None
        self.repairs += 1
        if self._on_repair is not None:
            self._on_repair(self)
