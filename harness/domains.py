"""ROS_DOMAIN_IDs handed out one per test, never shared while in use.

Each allocation holds an exclusive flock on ``LOCK_DIR/<id>.lock`` for as
long as it lives, so two pytest sessions on one machine (or two tests of one
session) never get the same domain and never see each other's nodes. A lock
held by a process that died is released by the kernel with it.

LOCK_DIR is ``cloneguard-domains`` in the system's temporary directory
(``tempfile.gettempdir()``: $TMPDIR, else /tmp), outside any project on
purpose: a ROS domain id is shared by every process on the machine, so
every checkout and venv running tests here must take its ids from the same
locks (runs given different $TMPDIRs do not see each other's). It holds
only the empty lock files, which are left for the next run.
"""

from __future__ import annotations

import fcntl
import os
import random
import tempfile
from pathlib import Path

# 0..101 is the range whose Fast DDS ports stay clear of Linux's ephemeral
# port range (ROS 2's own guidance). 0 is left alone: it is everyone's default.
DOMAIN_RANGE = range(1, 102)
LOCK_DIR = Path(tempfile.gettempdir()) / "cloneguard-domains"  # machine-wide: see above


class NoFreeDomain(RuntimeError):
    pass


class DomainLease:
    def __init__(self, domain_id: int, fd: int):
        self.domain_id = domain_id
        self._fd = fd

    def release(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)  # closing drops the flock
            self._fd = -1

    def __enter__(self) -> DomainLease:
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()


def lease(rng: random.Random | None = None) -> DomainLease:
    LOCK_DIR.mkdir(parents=True, exist_ok=True)
    ids = list(DOMAIN_RANGE)
    (rng or random.Random()).shuffle(ids)
    for domain_id in ids:
        fd = os.open(LOCK_DIR / f"{domain_id}.lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            continue
        return DomainLease(domain_id, fd)
    raise NoFreeDomain(f"all ROS domain ids {DOMAIN_RANGE.start}..{DOMAIN_RANGE.stop - 1} are in use")
