"""What the monitor reports, as Python values.

The C monitor writes fixed 40-byte records (struct cg_event) to a pipe; this
module turns one record into a Death or a StopRequested.
"""

from __future__ import annotations

import enum
import os
import signal as _signal
import struct
from dataclasses import dataclass
from typing import Union

# struct cg_event: kind pid status code serial t_ns repairs alloc
RECORD = struct.Struct("=IiiiQqII")
assert RECORD.size == 40

KIND_DEATH, KIND_STOP, KIND_CLOSED = 1, 2, 3
ALLOC_QUARANTINED = 1 << 31        # CG_ALLOC_QUARANTINED
ALLOC_SLOT_MASK = 0xFFFF
STOP_BY_PARENT, STOP_BY_SIGNAL = 1, 2


class Repair(enum.IntFlag):
    """What the monitor undid after a death, before reporting it (CG_REPAIR_*
    in clonecore.h; gilrepair.c says how)."""

    NONE = 0
    GIL_RELEASED = 1 << 0      # the dead task held the GIL: released
    GIL_MUTEX = 1 << 1         # it held gil->mutex: taken over, unlocked
    SWITCH_MUTEX = 1 << 2      # it held gil->switch_mutex: taken over, unlocked
    COND_WAITER = 1 << 3       # it was blocked on gil->cond: wait cancelled
    SWITCH_WAITER = 1 << 4     # it was blocked on gil->switch_cond: cancelled
    COND_LOCK = 1 << 5         # a GIL condvar's internal lock stayed taken
    GIL_TIMEOUT = 1 << 6       # gil->mutex stayed busy: the GIL was not checked

    def names(self) -> list[str]:
        """["GIL_RELEASED", ...]: the single flags set, in bit order."""
        return [m.name for m in Repair if m and m in self]


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
    alloc_slot: int = 0             # its allocator-guard slot, 0: no guard
    alloc_quarantined: bool = False # it died inside the allocator: its arena
                                    # is quarantined (allocguard.c)

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


CoreEvent = Union[Death, StopRequested]


def decode(buf: bytes) -> tuple[int, CoreEvent | None]:
    """One record -> (kind, event); event is None for KIND_CLOSED."""
    kind, pid, status, code, serial, t_ns, repairs, alloc = RECORD.unpack(buf)
    if kind == KIND_DEATH:
        exited = code == os.CLD_EXITED
        killed = code in (os.CLD_KILLED, os.CLD_DUMPED)
        return kind, Death(pid, serial,
                           exit_code=status if exited else None,
                           exit_signal=status if killed else None,
                           si_code=code,
                           core_dumped=code == os.CLD_DUMPED,
                           detected_monotonic_ns=t_ns,
                           repairs=Repair(repairs),
                           alloc_slot=alloc & ALLOC_SLOT_MASK,
                           alloc_quarantined=bool(alloc & ALLOC_QUARANTINED))
    if kind == KIND_STOP:
        by_signal = status == STOP_BY_SIGNAL
        sig = _signal.Signals(code) if by_signal and code > 0 else None
        return kind, StopRequested(pid, serial, by_signal, t_ns, sig)
    return kind, None
