"""A node's crash report, as the container wrote it on its log, with its
native frames named (symbols.py).

An isolated container writes a crashed node process's report in two parts
on its stderr (container/isolated/clonecore/crash.c, crash_reports.py): the head,
from the process itself as it dies (``cloneguard: pid PID caught SIGx at
... (pc ...)`` and the lines after it), and, after the CRASHED event, its
stacks (``cloneguard: pid PID Python stack ...`` then ``cloneguard: pid
PID native stack:`` and one line a frame). This module cuts one pid's
report out of the log for a person to read; nothing is judged from it.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable

from . import symbols

#: how long the stacks may take to follow the CRASHED event
STACKS_WAIT_S = 5.0
_FRAME = re.compile(r"^\S+\(.*\)\s*\[0x[0-9a-f]+\]\s*$")


def _block(lines: list[str], first: int, keep: Callable[[str], bool]) -> list[str]:
    """lines[first] and the lines right after it that ``keep`` accepts."""
    out = [lines[first]]
    for line in lines[first + 1 :]:
        if not keep(line):
            break
        out.append(line)
    return out


def report_of(log: str, pid: int) -> str | None:
    """The crash report of ``pid`` in ``log``: its head, Python stack and
    native stack (the parts there are so far), None if it has none. Other
    lines of the log may come between the parts; they are left out."""
    mine = f"cloneguard: pid {pid} "
    lines = log.splitlines()

    def find(prefix: str) -> int | None:
        return next((i for i, ln in enumerate(lines) if ln.startswith(prefix)), None)

    head = find(mine + "caught ")
    if head is None:
        return None
    # the head: its first line and the process's own lines after it
    out = _block(lines, head, lambda ln: ln.startswith("cloneguard: ") and not ln.startswith("cloneguard: pid "))
    python = find(mine + "Python stack")
    if python is not None:
        out += _block(lines, python, lambda ln: ln.startswith("  "))
    native = find(mine + "native stack:")
    if native is not None:
        out += _block(lines, native, lambda ln: bool(_FRAME.match(ln.strip())))
    return "\n".join(out) + "\n"


def has_native_stack(report: str | None, pid: int) -> bool:
    return report is not None and f"cloneguard: pid {pid} native stack:" in report


def wait_for_report(read_log: Callable[[], str], pid: int, timeout: float = STACKS_WAIT_S) -> str | None:
    """``pid``'s report once its native stack is on the log (or what there
    is after ``timeout``), its frames named where the libraries allow."""
    deadline = time.monotonic() + timeout
    while True:
        report = report_of(read_log(), pid)
        if has_native_stack(report, pid) or time.monotonic() >= deadline:
            return None if report is None else symbols.symbolize(report)
        time.sleep(0.05)
