"""Faults injected from outside the container: signals at chosen instants.

Every random choice comes from a ``random.Random`` the caller seeds, so a
trial can be replayed exactly.
"""

from __future__ import annotations

import os
import signal
import time


def kill_at(pid: int, sig: int, delay_s: float) -> int:
    """Sleep ``delay_s``, then send ``sig`` to ``pid``; time.time_ns() of the send."""
    time.sleep(delay_s)
    sent = time.time_ns()
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass
    return sent


def sigkill_container(proc) -> int:
    """SIGKILL the container process itself (not its group): nothing of its
    own shutdown runs; its children follow by PR_SET_PDEATHSIG."""
    sent = time.time_ns()
    proc.signal(signal.SIGKILL)
    return sent
