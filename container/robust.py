"""Robust mutexes in container memory, shared by the container and children.

A pthread mutex with PTHREAD_MUTEX_ROBUST: if its owner (a child, or a thread
of the container) dies holding it, the kernel marks it and the next locker is
told (EOWNERDEAD) instead of hanging forever.  That locker owns it, must bring
the protected state back to something sane and mark it consistent; if it
unlocks without doing so the mutex becomes unusable for good
(ENOTRECOVERABLE).  Isolated children register their robust list at start
(see isolated/clonecore/child.c), which is what makes this work for them.  The C
(robust.c) is an extension of its own: thread mode needs no clone core.

Blocking happens in C with the GIL released (cffi API mode does that for every
call), so other Python threads and children go on meanwhile.

The object must outlive every user: the memory is freed when it is garbage
collected.  Keep it referenced from whatever the child runs.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from ._robust import ffi, lib


class MutexNotRecoverable(RuntimeError):
    """An earlier owner died and nobody marked the mutex consistent."""


class RobustMutex:
    """Robust, error-checking mutex.

    ``repair`` runs (with the mutex held) when ``with mutex:`` finds that the
    previous owner died; None means the protected state needs no repair.
    """

    def __init__(self, repair: Callable[[], None] | None = None) -> None:
        m = lib.rm_new()
        if m == ffi.NULL:
            raise MemoryError("cannot create a robust mutex")
        self._m = ffi.gc(m, lib.rm_free)
        self.repair = repair

    def lock(self, timeout: float | None = None) -> bool:
        """Lock; True if the previous owner died holding it.

        On True the caller owns the mutex and must repair, ``mark_consistent()``
        and ``unlock()``.  Raises TimeoutError, MutexNotRecoverable, or
        RuntimeError if this thread already holds it.
        """
        ns = -1 if timeout is None else max(0, int(timeout * 1e9))
        rc = lib.rm_lock(self._m, ns)
        return self._result(rc)

    def mark_consistent(self) -> None:
        self._check(lib.rm_consistent(self._m), "mark_consistent")

    def unlock(self) -> None:
        self._check(lib.rm_unlock(self._m), "unlock")

    def acquire(self, timeout: float | None = None, repair: Callable[[], None] | None = None) -> bool:
        """Lock; if the owner had died, repair and mark consistent first.

        Returns whether a repair happened.  If the repair raises, the mutex is
        unlocked without being marked consistent (so it becomes unusable:
        better than handing out state nobody could fix) and the error
        propagates.
        """
        died = self.lock(timeout)
        if died:
            fix = repair or self.repair
            try:
                if fix is not None:
                    fix()
            except BaseException:
                self.unlock()
                raise
            self.mark_consistent()
        return died

    @contextmanager
    def held(self, timeout: float | None = None, repair: Callable[[], None] | None = None) -> Iterator[bool]:
        """``with m.held(timeout, repair) as repaired:`` -- see acquire()."""
        repaired = self.acquire(timeout, repair)
        try:
            yield repaired
        finally:
            self.unlock()

    def __enter__(self) -> bool:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.unlock()

    @staticmethod
    def _result(rc: int) -> bool:
        if rc == 0:
            return False
        if rc == errno.EOWNERDEAD:
            return True
        if rc == errno.ETIMEDOUT:
            raise TimeoutError("robust mutex: timed out")
        if rc == errno.ENOTRECOVERABLE:
            raise MutexNotRecoverable("robust mutex: a previous owner died and the state was never marked consistent")
        if rc == errno.EDEADLK:
            raise RuntimeError("robust mutex: already held by this thread")
        raise OSError(rc, os.strerror(rc))

    @staticmethod
    def _check(rc: int, what: str) -> None:
        if rc != 0:
            raise OSError(rc, f"robust mutex {what}: {os.strerror(rc)}")
