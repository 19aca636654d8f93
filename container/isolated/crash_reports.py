"""The second half of a crashed child's report: its native stack, symbolized
and written by the container once the death has been reported.

A child that crashes (SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGABRT) writes the
first half itself, on its way out: the signal, the address, its Python
stack. It unwinds its native stack too, but leaves the raw addresses in its
control block instead of symbolizing them, because symbolizing took most of
the report's time and the death could not be reported before the report was
done (crash.c). The container shares the address space, so the same
addresses name the same code here; it writes them, one line per frame, as
``cloneguard: pid PID native stack:`` followed by backtrace_symbols_fd's
lines, on the same stream (fd 2) after the node's CRASHED event.

Symbolizing takes the dynamic loader's lock, which a node that died inside
the loader could have left taken: it runs on a thread of its own, so at
worst that thread waits, never one the container needs.
"""
from __future__ import annotations

import os
import queue
import threading

STDERR = 2


class NativeStacks:
    def __init__(self, lib, ffi, fd: int = STDERR):
        self._lib, self._ffi, self._fd = lib, ffi, fd
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._pending = 0
        self._done = threading.Condition()
        self._thread: threading.Thread | None = None

    def frames_of(self, block) -> tuple[int, ...]:
        """The native frames a dead child's crash report left (none if it
        wrote no report, or wrote it whole itself)."""
        n = block.crash_nframes
        if n <= 0:
            return ()
        return tuple(int(self._ffi.cast("uintptr_t", block.crash_frames[i])) for i in range(n))

    def submit(self, pid: int, frames: tuple[int, ...]) -> None:
        with self._done:
            self._pending += 1
            if self._thread is None:
                self._thread = threading.Thread(target=self._write_all, name="cloneguard-native-stacks",
                                                daemon=True)
                self._thread.start()
        self._queue.put((pid, frames))

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every submitted stack is written; False on timeout."""
        with self._done:
            return self._done.wait_for(lambda: self._pending == 0, timeout)

    def close(self, timeout: float | None = None) -> bool:
        """Write what was submitted (False if that took longer than
        ``timeout``), then end the writer thread."""
        done = self.flush(timeout)
        with self._done:
            thread, self._thread = self._thread, None
        if thread is not None:
            self._queue.put(None)
            if done:
                thread.join()
        return done

    def _write_all(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            pid, frames = item
            try:
                os.write(self._fd, f"cloneguard: pid {pid} native stack:\n".encode())
                array = self._ffi.new("void *[]", [self._ffi.cast("void *", f) for f in frames])
                self._lib.cg_write_native_stack(array, len(frames), self._fd)
            except OSError:
                pass                    # stderr is gone: nowhere to write
            finally:
                with self._done:
                    self._pending -= 1
                    self._done.notify_all()
