"""What the monitor reports, as Python values.

The C monitor writes fixed 32-byte records (struct cg_event) to a pipe; this
module turns one record into a Death or a StopRequested.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from typing import Union

RECORD = struct.Struct("=IiiiQq")   # struct cg_event: kind pid status code serial t_ns
assert RECORD.size == 32

KIND_DEATH, KIND_STOP, KIND_CLOSED = 1, 2, 3
STOP_BY_PARENT, STOP_BY_SIGNAL = 1, 2


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

    @property
    def status_lost(self) -> bool:
        return self.si_code == 0


@dataclass(frozen=True)
class StopRequested:
    """A child's stop flag was set, by SIGTERM to it or by the parent."""

    pid: int
    serial: int
    by_signal: bool
    detected_monotonic_ns: int


CoreEvent = Union[Death, StopRequested]


def decode(buf: bytes) -> tuple[int, CoreEvent | None]:
    """One record -> (kind, event); event is None for KIND_CLOSED."""
    kind, pid, status, code, serial, t_ns = RECORD.unpack(buf)
    if kind == KIND_DEATH:
        exited = code == os.CLD_EXITED
        killed = code in (os.CLD_KILLED, os.CLD_DUMPED)
        return kind, Death(pid, serial,
                           exit_code=status if exited else None,
                           exit_signal=status if killed else None,
                           si_code=code,
                           core_dumped=code == os.CLD_DUMPED,
                           detected_monotonic_ns=t_ns)
    if kind == KIND_STOP:
        return kind, StopRequested(pid, serial, status == STOP_BY_SIGNAL, t_ns)
    return kind, None
