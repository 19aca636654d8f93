"""The second half of a crashed child's report: its Python and native
stacks, written by the container once the death has been reported.

A child that crashes (SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGABRT) writes the
report's head itself, on its way out: the signal, the address. Its stacks
it only records in its control block: each Python frame's code object and
instruction offset, and the native frames' addresses (crash.c), because
writing them took most of the report's time and the death could not be
reported before the report was done. The container shares the address
space, so the same pointers mean the same here; it writes, on the same
stream (fd 2) after the node's CRASHED event::

    cloneguard: pid PID Python stack (most recent call first):
      File "...", line N in name            (as faulthandler writes them)
    cloneguard: pid PID native stack:
    ...                                     (backtrace_symbols_fd's lines)

The code objects are held (a reference of the container's) from the moment
the death is seen until they are written. Symbolizing takes the dynamic
loader's lock, which a node that died inside the loader could have left
taken: the writing runs on a thread of its own, so at worst that thread
waits, never one the container needs.
"""

from __future__ import annotations

import os
import queue
import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing import Any

STDERR = 2


@dataclass(frozen=True)
class RecordedStacks:
    """What a dead child's crash report recorded: raw pointers into the
    shared address space (code objects held by ``CrashStacks.take``)."""

    native: tuple[int, ...]
    py_codes: tuple[int, ...]
    py_lasti: tuple[int, ...]
    py_more: bool


class CrashStacks:
    def __init__(self, lib: Any, ffi: Any, fd: int = STDERR) -> None:
        self._lib, self._ffi, self._fd = lib, ffi, fd
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._pending = 0
        self._done = threading.Condition()
        self._thread: threading.Thread | None = None

    def take(self, block: Any) -> RecordedStacks | None:
        """The stacks a dead child's crash report recorded, its code objects
        held; None if it wrote no report, or wrote it whole itself."""
        ffi = self._ffi
        n = block.crash_nframes
        if n <= 0:
            return None
        m = block.crash_py_nframes
        codes = tuple(int(ffi.cast("uintptr_t", block.crash_py_code[i])) for i in range(m))
        self._lib.cg_hold_py_stack(block.crash_py_code, m, 1)
        return RecordedStacks(
            native=tuple(int(ffi.cast("uintptr_t", block.crash_frames[i])) for i in range(n)),
            py_codes=codes,
            py_lasti=tuple(block.crash_py_lasti[i] for i in range(m)),
            py_more=bool(block.crash_py_more),
        )

    def submit(self, pid: int, stacks: RecordedStacks) -> None:
        with self._done:
            self._pending += 1
            if self._thread is None:
                self._thread = threading.Thread(target=self._write_all, name="cloneguard-crash-stacks", daemon=True)
                self._thread.start()
        self._queue.put((pid, stacks))

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every submitted report is written; False on timeout."""
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
            pid, stacks = item
            try:
                self._write(pid, stacks)
            except OSError:
                pass  # stderr is gone: nowhere to write
            finally:
                with self._done:
                    self._pending -= 1
                    self._done.notify_all()

    def _write(self, pid: int, stacks: RecordedStacks) -> None:
        ffi, lib = self._ffi, self._lib
        n = len(stacks.py_codes)
        if n:
            codes = ffi.new("void *[]", [ffi.cast("void *", c) for c in stacks.py_codes])
            try:
                os.write(self._fd, f"cloneguard: pid {pid} Python stack (most recent call first):\n".encode())
                lasti = ffi.new("int[]", list(stacks.py_lasti))
                lib.cg_write_py_stack(codes, lasti, n, int(stacks.py_more), self._fd)
            finally:
                lib.cg_hold_py_stack(codes, n, 0)  # the references take() took
        else:
            os.write(self._fd, f"cloneguard: pid {pid} Python stack: none (no Python frame)\n".encode())
        os.write(self._fd, f"cloneguard: pid {pid} native stack:\n".encode())
        native = ffi.new("void *[]", [ffi.cast("void *", f) for f in stacks.native])
        lib.cg_write_native_stack(native, len(stacks.native), self._fd)
