"""A child of the clone core caught while it waits for the GIL, for the tests
of what such a waiter leaves behind (test_isolated_gil.py, test_core_dumps.py)."""

from __future__ import annotations

import ctypes
import subprocess
import threading
import time


def spawn_busy(core):
    """A child that runs Python without end, once it has begun."""
    running = threading.Event()

    def child():
        running.set()
        while True:
            sum(range(10))

    c = core.spawn(child)
    assert running.wait(10)
    return c


def signal_while_gil_held(pid: int, sig: str) -> None:
    """Send `sig` (a kill(1) name) to `pid` while this thread holds the GIL
    in a C call (ctypes.PyDLL keeps it), so that a busy child is blocked in
    take_gil's wait on gil->cond when it comes."""
    killer = subprocess.Popen(["sh", "-c", f"sleep 0.3; kill -{sig} {pid}"])
    ctypes.PyDLL(None).usleep(800_000)
    assert killer.wait(10) == 0


class Counter:
    """A Python thread of the container that counts while the GIL is free."""

    def __init__(self) -> None:
        self.value = 0
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop:
            self.value += 1

    def advances(self, timeout: float = 5.0) -> bool:
        start = self.value
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            time.sleep(0.005)
            if self.value != start:
                return True
        return False

    def stop(self) -> None:
        self._stop = True
        self._thread.join(5)
