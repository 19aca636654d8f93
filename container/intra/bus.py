"""The container's intra-process bus: who publishes and subscribes to what.

One bus per container (per interpreter), created by the container before it
starts any child, so it is container-owned memory every child sees. It holds
the intra-process subscriptions by topic (with their queues and how to wake
them) and the DDS gids of the intra-process publishers by topic (so a
subscription can drop the DDS copy of a message it already got by reference).

Readers (every publish) look entries up without locking: each topic's entry
is an immutable tuple replaced by one dict store. Writers (create, destroy,
a node's unload or death) take the bus's robust mutex; a writer that dies
mid-change leaves either the old tuple or the new one.

It also holds the wakers (waker.py) of the node processes the container
opened them for: the isolated host opens one before it starts a node that
uses intra-process messaging; the node's unload or death closes it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rclpy.logging import get_logger

from cloneguard.container.robust import RobustMutex

from .pool import LoanPool
from .queue import MessageQueue
from .waker import Waker

log = get_logger("cloneguard.intra")


@dataclass(eq=False)
class SubscriptionEntry:
    owner: Any  # the load's unique_id, or None outside a container
    topic: str
    msg_type: type
    reliable: bool  # asks for RELIABLE: a BEST_EFFORT publisher does not match
    queue: MessageQueue
    wake: Callable[[], None]  # wakes the subscription's executor (waker.py)

    def matches(self, pub: PublisherEntry) -> bool:
        return pub.msg_type is self.msg_type and not (self.reliable and pub.best_effort)


@dataclass(eq=False)
class PublisherEntry:
    owner: Any
    topic: str
    msg_type: type
    best_effort: bool
    gid: bytes = field(repr=False, default=b"")


class Bus:
    def __init__(self) -> None:
        self._mutex = RobustMutex(self._repaired)
        self._subs: dict[str, tuple[SubscriptionEntry, ...]] = {}
        self._pubs: dict[str, tuple[PublisherEntry, ...]] = {}
        self._pub_gids: dict[str, frozenset[bytes]] = {}
        self.pool = LoanPool()
        self.repairs = 0
        self._wakers: dict[object, Waker] = {}
        self.stuck_wakers = 0

    # -- lock-free reads (every publish, every DDS sample) ---------------------

    def subscriptions(self, topic: str) -> tuple[SubscriptionEntry, ...]:
        return self._subs.get(topic, ())

    def targets(self, pub: PublisherEntry) -> list[SubscriptionEntry]:
        return [s for s in self._subs.get(pub.topic, ()) if s.matches(pub)]

    def is_intra_publisher(self, topic: str, gid: bytes) -> bool:
        return gid in self._pub_gids.get(topic, ())

    # -- wakers (container threads only open and close them) ---------------------

    def open_waker(self, owner: object) -> Waker:
        waker = self._wakers.get(owner)
        if waker is None:
            waker = self._wakers[owner] = Waker()
        return waker

    def waker(self, owner: object) -> Waker | None:
        return self._wakers.get(owner)

    def _close_waker(self, owner: object) -> None:
        waker = self._wakers.pop(owner, None)
        if waker is not None and not waker.close():
            self.stuck_wakers += 1
            log.warning(
                f"intra-process waker of unique_id {owner}: stuck in its dead subscriber's wait-set lock; left behind"
            )

    # -- changes (robust mutex) --------------------------------------------------

    def add_subscription(self, entry: SubscriptionEntry) -> None:
        with self._mutex:
            self._subs[entry.topic] = self._subs.get(entry.topic, ()) + (entry,)

    def add_publisher(self, entry: PublisherEntry) -> None:
        with self._mutex:
            self._pubs[entry.topic] = self._pubs.get(entry.topic, ()) + (entry,)
            self._pub_gids[entry.topic] = self._pub_gids.get(entry.topic, frozenset()) | {entry.gid}

    def remove(self, entry: SubscriptionEntry | PublisherEntry) -> None:
        with self._mutex:
            self._drop(lambda e: e is entry, {entry.topic})

    def forget(self, owner: object) -> int:
        """Remove every endpoint of one loaded node (unloaded, or its process
        died): publishers stop queueing to its subscriptions and waking them,
        and its gids stop being filtered. Returns how many were removed."""
        if owner is None:
            return 0
        with self._mutex:
            removed = self._drop(lambda e: e.owner == owner, set(self._subs) | set(self._pubs))
        self._close_waker(owner)
        return removed

    def _drop(self, doomed: Callable[[Any], bool], topics: set[str]) -> int:
        removed = 0
        for topic in topics:
            subs = self._subs.get(topic, ())
            keep = tuple(s for s in subs if not doomed(s))
            removed += len(subs) - len(keep)
            self._set(self._subs, topic, keep)
            pubs = self._pubs.get(topic, ())
            keep_p = tuple(p for p in pubs if not doomed(p))
            if len(keep_p) != len(pubs):
                removed += len(pubs) - len(keep_p)
                self._set(self._pubs, topic, keep_p)
                self._set(self._pub_gids, topic, frozenset(p.gid for p in keep_p))
        return removed

    @staticmethod
    def _set(
        table: dict, topic: str, value: tuple[SubscriptionEntry, ...] | tuple[PublisherEntry, ...] | frozenset[bytes]
    ) -> None:
        if value:
            table[topic] = value
        else:
            table.pop(topic, None)

    def _repaired(self) -> None:
        # Every change is one dict store of a whole new tuple: nothing to undo.
        self.repairs += 1
        log.warning(
            "intra-process bus: the owner of its lock died holding it (EOWNERDEAD); state is consistent, lock recovered"
        )


_bus: Bus | None = None
_bus_lock = threading.Lock()


def get_bus() -> Bus:
    """The container's bus, created on first use (the container calls this
    at start, before any child exists)."""
    global _bus
    if _bus is None:
        with _bus_lock:
            if _bus is None:
                _bus = Bus()
    return _bus
