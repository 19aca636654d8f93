"""SIGINT/SIGTERM as a stop request the container's main thread waits for.

rclpy's own signal handling is not used: on a signal it shuts down every
rclpy Context in the process, and in isolated mode that includes the
contexts of nodes running in children, which would then stop on their own
while the container is still deciding how to stop them. Here a signal only
wakes the main thread (Python's wakeup fd, written by the C-level handler on
whatever thread the kernel picked), and the container stops in its own order.
"""

from __future__ import annotations

import os
import signal
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from types import FrameType

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class StopSignals:
    def __init__(self) -> None:
        self._r, self._w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        os.set_blocking(self._r, True)
        self._previous = {sig: signal.signal(sig, self._ignore) for sig in STOP_SIGNALS}
        self._previous_fd = signal.set_wakeup_fd(self._w, warn_on_full_buffer=False)

    @staticmethod
    def _ignore(signum: int, frame: FrameType | None) -> None:
        pass  # the wakeup fd already carries it

    def post(self, why: int = 0) -> None:
        """Wake :meth:`wait` without a signal (e.g. the executor thread died)."""
        try:
            os.write(self._w, bytes([why]))
        except BlockingIOError:
            pass  # a wake-up is already pending

    def wait(self) -> int:
        """Block until a stop signal (or post); return the signal number (0 for post)."""
        return os.read(self._r, 1)[0]

    def close(self) -> None:
        signal.set_wakeup_fd(self._previous_fd)
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        os.close(self._r)
        os.close(self._w)
