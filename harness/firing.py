"""The line a fault component writes just before its fault fires, defined
once: written by the fault components (faults/components.py) into the
container's log, read back by the rig (harness/rig.py) to time the fault
against the CRASHED event's stamp (the same host clock).

    cloneguard-fault: <fault> firing at <time.time_ns()> pid <pid>
"""

from __future__ import annotations

import re
from collections.abc import Iterator

MARK = "cloneguard-fault:"
_LINE = re.compile(r"^" + re.escape(MARK) + r" (\S+) firing at (\d+) pid (\d+)$", re.M)


def line(fault: str, time_ns: int, pid: int) -> bytes:
    """The whole line, to be written with one write(2)."""
    if not fault or any(c.isspace() for c in fault):
        raise ValueError(f"a fault name is one word, got {fault!r}")
    return f"{MARK} {fault} firing at {time_ns} pid {pid}\n".encode()


def parse(log: str) -> Iterator[tuple[str, int, int]]:
    """(fault, time_ns, pid) of every such line in ``log``."""
    for m in _LINE.finditer(log):
        yield m.group(1), int(m.group(2)), int(m.group(3))
