"""What the monitor reports, as Python values.

The C monitor writes fixed records (``struct cg_event``, core.h) to a pipe;
this module turns one record into a Death, a StopRequested or a
MutexReport. The record's
layout and every constant come from the built core (its cffi module), so
they are written once, in core.h and repair.h.
"""

from __future__ import annotations

import enum
import os
import signal as _signal
from dataclasses import dataclass

from cloneguard.container.isolated._clonecore import ffi, lib

RECORD_SIZE = ffi.sizeof("struct cg_event")
KIND_DEATH, KIND_STOP, KIND_CLOSED, KIND_MUTEX = lib.CG_EV_DEATH, lib.CG_EV_STOP, lib.CG_EV_CLOSED, lib.CG_EV_MUTEX
STOP_BY_PARENT, STOP_BY_SIGNAL = lib.CG_STOP_PARENT, lib.CG_STOP_SIGNAL


class Repair(enum.IntFlag):
    """What the monitor undid after a death, before reporting it: repair.h's
    CG_REPAIRS, by name and bit (tests/test_herald.py checks these members
    against the core's cg_repair_name); gilrepair.c and interp.c say how."""

    NONE = 0
    GIL_RELEASED = lib.CG_REPAIR_GIL_RELEASED  # the dead task held the GIL: released
    GIL_MUTEX = lib.CG_REPAIR_GIL_MUTEX  # it held gil->mutex: taken over, unlocked
    SWITCH_MUTEX = lib.CG_REPAIR_SWITCH_MUTEX  # it held gil->switch_mutex: taken over, unlocked
    COND_WAITER = lib.CG_REPAIR_COND_WAITER  # it was blocked on gil->cond: wait cancelled
    SWITCH_WAITER = lib.CG_REPAIR_SWITCH_WAITER  # it was blocked on gil->switch_cond: cancelled
    COND_LOCK = lib.CG_REPAIR_COND_LOCK  # a GIL condvar's internal lock stayed taken
    GIL_TIMEOUT = lib.CG_REPAIR_GIL_TIMEOUT  # gil->mutex stayed busy: the GIL was not checked
    PY_POOLS = lib.CG_REPAIR_PY_POOLS  # it held the GIL: its Python object pools abandoned
    GC_LINKS = lib.CG_REPAIR_GC_LINKS  # ... a half-updated link of the young generation mended
    FREELISTS = lib.CG_REPAIR_FREELISTS  # ... the interpreter's free lists emptied
    PY_OBJECTS = lib.CG_REPAIR_PY_OBJECTS  # ... objects it may have been changing put
    #     out of the collector's sight

    def names(self) -> list[str]:
        """["GIL_RELEASED", ...]: the single flags set, in bit order (as the
        core's words for a death name them, deathtext.c)."""
        return [m.name or "" for m in Repair if m and m in self]


#: What is mended in the interpreter after a death with the GIL held
#: (interp.c), beside the GIL itself.
INTERPRETER_REPAIRS = Repair.PY_POOLS | Repair.GC_LINKS | Repair.FREELISTS | Repair.PY_OBJECTS


@dataclass(frozen=True)
class PkeyFault:
    """A write the PKRU forbade (SIGSEGV, SEGV_PKUERR): where, under which
    key, and whose memory that is: the slot whose range holds the address
    (a node's native heap) and the pid bound to it then (0 if none), slot
    0 for the allocator guard's own tables, -1 for neither."""

    addr: int
    key: int
    victim_slot: int
    victim_pid: int


@dataclass(frozen=True)
class Death:
    """A child was reaped.

    exit_code is set for a normal exit (si_code CLD_EXITED), exit_signal for
    a death by signal (CLD_KILLED, CLD_DUMPED).  si_code 0 means something
    else in the container reaped the child first (a stray waitpid(-1)): it is
    dead, the status is lost.
    """

    pid: int
    serial: int
    exit_code: int | None
    exit_signal: int | None
    si_code: int
    core_dumped: bool
    detected_monotonic_ns: int
    repairs: Repair = Repair.NONE
    alloc_slot: int = 0  # its allocator-guard slot, 0: no guard
    alloc_quarantined: bool = False  # its arena is quarantined (allocguard.c):
    alloc_faulted: bool = False  # for a fault of its own; else it died inside malloc
    py_abandoned: bool = False  # it died inside CPython's object
    # allocator: its pools are abandoned (pyalloc.c)
    over_budget: bool = False  # it ended itself over its memory budget (allocguard.c)
    out_of_memory: bool = False  # the memory watch ended it: the container's
    # memory was near its limit, and it used the most (memwatch.c)
    gil_frame: str = ""  # it held the GIL: "function (file:line)"
    # of its innermost Python frame
    pkey_fault: PkeyFault | None = None  # it died writing under a
    # protection key not its own (heapkeys.c)
    core_file: str = ""  # --core-dumps: the dump written of it (dumps.c),
    core_missing: str = ""  # or why it asked for one and got none
    text: str = ""  # what the core says of it (cg_describe_death, deathtext.c)
    claimed: bool = False  # the herald published its CRASHED event

    @property
    def status_lost(self) -> bool:
        return self.si_code == 0

    @property
    def gil_repaired(self) -> bool:
        """The child died holding the GIL and the monitor released it."""
        return Repair.GIL_RELEASED in self.repairs

    @property
    def repaired(self) -> bool:
        """Anything at all was repaired after this death."""
        return bool(self.repairs & ~Repair.GIL_TIMEOUT)


@dataclass(frozen=True)
class StopRequested:
    """A child's stop flag was set, by SIGTERM or SIGINT to it, or by the
    parent (then ``signal`` is None)."""

    pid: int
    serial: int
    by_signal: bool
    detected_monotonic_ns: int
    signal: int | None = None


RWLOCK_KIND = lib.CG_RWLOCK_KIND  # MutexReport.mutex_kind of a pthread rwlock


class MutexVerdict(enum.IntEnum):
    """What the lock doctor did about a task blocked on a lock (CG_MUTEX_*
    in core.h; mutexes.c says when each applies)."""

    RELEASED = lib.CG_MUTEX_RELEASED  # a plain mutex of a proven-dead owner: released
    UNPROVEN = lib.CG_MUTEX_UNPROVEN  # its owner is gone, not proven a dead node's task
    NO_OWNER = lib.CG_MUTEX_NO_OWNER  # held with no owner recorded, for over a second
    EXCLUDED = lib.CG_MUTEX_EXCLUDED  # a dead owner's robust/PI/shared/elided mutex
    LIBC_LOCK = lib.CG_MUTEX_LIBC_LOCK  # a glibc-internal lock, waited on for over a second


@dataclass(frozen=True)
class MutexReport:
    """A live task is (was) blocked on a native lock after a node process
    died. ``pid``/``serial`` name the dead child that held it (RELEASED,
    EXCLUDED), else the last child to die."""

    pid: int
    serial: int
    verdict: MutexVerdict
    address: int  # the lock word's
    waiter_tid: int
    owner_tid: int  # 0: none recorded
    mutex_kind: int  # __data.__kind; -1: not a pthread mutex (glibc-internal); RWLOCK_KIND: a rwlock
    detected_monotonic_ns: int


CoreEvent = Death | StopRequested | MutexReport


def decode(buf: bytes) -> tuple[int, CoreEvent | None]:
    """One record -> (kind, event); event is None for KIND_CLOSED."""
    r = ffi.cast("struct cg_event *", ffi.from_buffer(buf))
    kind, code = r.kind, r.code
    if kind == KIND_DEATH:
        exited = code == os.CLD_EXITED
        killed = code in (os.CLD_KILLED, os.CLD_DUMPED)
        return kind, Death(
            r.pid,
            r.serial,
            exit_code=r.status if exited else None,
            exit_signal=r.status if killed else None,
            si_code=code,
            core_dumped=code == os.CLD_DUMPED,
            detected_monotonic_ns=r.t_ns,
            repairs=Repair(r.repairs),
            alloc_slot=r.alloc & lib.CG_ALLOC_SLOT_MASK,
            alloc_quarantined=bool(r.alloc & lib.CG_ALLOC_QUARANTINED),
            alloc_faulted=bool(r.alloc & lib.CG_ALLOC_FAULTED),
            py_abandoned=bool(r.alloc & lib.CG_ALLOC_PY_ABANDONED),
            over_budget=bool(r.alloc & lib.CG_ALLOC_OVER_BUDGET),
            claimed=bool(r.flags & lib.CG_EVF_CLAIMED),
            out_of_memory=bool(r.flags & lib.CG_EVF_OUT_OF_MEMORY),
        )
    if kind == KIND_STOP:
        by_signal = r.status == STOP_BY_SIGNAL
        sig = _signal.Signals(code) if by_signal and code > 0 else None
        return kind, StopRequested(r.pid, r.serial, by_signal, r.t_ns, sig)
    if kind == KIND_MUTEX:
        return kind, MutexReport(
            r.pid, r.serial, MutexVerdict(r.status), r.addr, r.tid, r.owner, r.code, detected_monotonic_ns=r.t_ns
        )
    return kind, None
