"""The lock doctor's reports (mutexes.c) in words, and where they go.

A native mutex released after its owner's process died is a repair like the
container's others: recorded (repairs.py) and published as a ComponentEvent
REPAIRED, ``repaired_state`` ``"native-mutex"``, for the node that held it.
What was not released (not proven, excluded, no owner recorded, a glibc
internal lock) is said on the container's log: a warning naming the lock,
where it lies, who waits on it and the dead holder, so a hang is never
silent.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .. import processes, repairs
from .core_events import RWLOCK_KIND, MutexReport, MutexVerdict
from .mappings import describe

if TYPE_CHECKING:
    from typing import Protocol

    class _Log(Protocol):
        """Where ``handle`` says what it did not repair: a logger with .warning."""

        def warning(self, message: str, /) -> object: ...


_TYPES = ("NORMAL", "RECURSIVE", "ERRORCHECK", "ADAPTIVE")
_FLAGS = (
    (16, "robust"),
    (32, "priority-inheritance"),
    (64, "priority-protect"),
    (128, "process-shared"),
    (256, "elided"),
)


def kind_name(kind: int) -> str:
    """__data.__kind in words: "RECURSIVE", "robust NORMAL", ...; -1: a
    glibc-internal lock; RWLOCK_KIND: a pthread rwlock."""
    if kind == RWLOCK_KIND:
        return "rwlock"
    if kind < 0:
        return "glibc-internal lock"
    flags = [name for bit, name in _FLAGS if kind & bit]
    return " ".join([*flags, _TYPES[kind & 3]])


def _tgid(tid: int) -> int:
    try:
        with open(f"/proc/{tid}/status") as f:
            for line in f:
                if line.startswith("Tgid:"):
                    return int(line.split()[1])
    except (OSError, ValueError):
        pass
    return 0


def text(r: MutexReport) -> str:
    """One sentence: what the lock is, where it lies, who waits, who held it,
    and what the container did."""
    tgid = _tgid(r.waiter_tid)
    waiter = f"{processes.who(tgid)} thread {r.waiter_tid}" if tgid else f"thread {r.waiter_tid}"
    rwlock = r.mutex_kind == RWLOCK_KIND
    if rwlock:
        lock = f"rwlock {r.address:#x}"
    elif r.mutex_kind >= 0:
        lock = f"{kind_name(r.mutex_kind)} mutex {r.address:#x}"
    else:
        lock = f"glibc-internal lock {r.address:#x}"
    where = describe(r.address)
    dead = processes.who(r.pid) if r.pid else "a node process"
    if rwlock and r.verdict == MutexVerdict.RELEASED:
        return (
            f"native {lock} in {where}, write-locked by {dead} thread {r.owner_tid} when its process died, was "
            f"released for {waiter}; what it guards may be half-updated"
        )
    if rwlock and r.verdict == MutexVerdict.EXCLUDED:
        return (
            f"{waiter} is blocked on native {lock} in {where}, write-locked by {dead} thread {r.owner_tid} when its "
            "process died: not released (process-shared, or not in the state its writer leaves it in)"
        )
    if rwlock and r.verdict == MutexVerdict.NO_OWNER:
        return (
            f"{waiter} has been blocked for over a second on native {lock} in {where}, held by readers or with no "
            f"writer recorded (glibc records no reader: a dead reader cannot be told from a live one; the last node "
            f"process to die was {dead}): not released"
        )
    if r.verdict == MutexVerdict.RELEASED and not r.waiter_tid:
        return (
            f"native {lock} in {where}, still held by {dead} thread {r.owner_tid} a second after its process died, "
            "with no task blocked on it (a waiter that polls with trylock never blocks), was released; what it "
            "guards may be half-updated"
        )
    if r.verdict == MutexVerdict.RELEASED:
        return (
            f"native {lock} in {where}, held by {dead} thread {r.owner_tid} when its process died, was released "
            f"for {waiter}; what it guards may be half-updated"
        )
    if r.verdict == MutexVerdict.EXCLUDED:
        return (
            f"{waiter} is blocked on native {lock} in {where}, held by {dead} thread {r.owner_tid} when its process "
            "died: not released (only plain private mutexes are)"
        )
    if r.verdict == MutexVerdict.UNPROVEN:
        return (
            f"{waiter} is blocked on native {lock} in {where}, whose owner thread {r.owner_tid} is gone but was not "
            "seen in a dead node process: not released"
        )
    if r.verdict == MutexVerdict.NO_OWNER:
        return (
            f"{waiter} has been blocked for over a second on native {lock} in {where}, held with no owner recorded "
            f"(its owner may have died taking or releasing it; the last node process to die was {dead}): not released"
        )
    return (
        f"{waiter} has been blocked for over a second on a {lock} in {where} (glibc records no owner) since "
        f"{dead} died: that process may have died holding it; not released"
    )


def handle(r: MutexReport, log: _Log) -> None:
    """Record a release as a repair (published REPAIRED); say the rest on
    ``log`` (a logger with .warning)."""
    sentence = text(r)
    if r.verdict == MutexVerdict.RELEASED:
        unique_id, _ = processes.node_of(r.pid)
        repairs.record(repairs.NATIVE_MUTEX, unique_id, sentence)
        log.warning(sentence)
    else:
        log.warning(f"{repairs.NOT_REPAIRED}{sentence}")
