"""The isolated container's watchdog clock (container/watchdog.py's
``Clock``): CLOCK_MONOTONIC less the time the monitor had a core dump asked
for or under way (dumps.c), and the clone core's own last-resort thread
(lastresort.c), which reads that clock where faulthandler's would not.

A node that crashed holding the GIL keeps it until gdb has written its dump
(--core-dumps; seconds), and no Python runs meanwhile: on this clock that
time does not pass, so the watchdog does not take it for a hang.
"""

from __future__ import annotations

import os
import sys

from cloneguard.container.isolated._clonecore import lib


class DumpPausedClock:
    def __init__(self, banner: str):
        rc = lib.cg_lastresort_start(sys.stderr.fileno(), banner.encode())
        if rc < 0:
            raise OSError(-rc, f"the watchdog's last-resort thread did not start: {os.strerror(-rc)}")

    def now(self) -> float:
        """The watch clock, in seconds."""
        return lib.cg_watch_clock_ns() / 1e9

    def arm_last_resort(self, after_s: float) -> None:
        lib.cg_lastresort_arm(int(after_s * 1e9))

    def close(self) -> None:
        lib.cg_lastresort_stop()
