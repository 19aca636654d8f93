"""Loaned buffers for large payloads: container-owned, recycled, never malloc'd.

A publisher that loans a buffer writes its payload straight into memory the
container owns (an anonymous mmap per block, kept for reuse), and the
subscribers read that same memory. When the last holder lets go, the block
goes back to the pool's free list: releasing a message takes the pool's
robust mutex, never the malloc arena lock of the process that published it.
That is the point: with malloc'd payloads, a subscriber freeing a message
whose publisher was SIGKILLed inside malloc() waits on that dead process's
arena lock forever (see scenarios/test_intra_process.py, which measures it).

Blocks come in power-of-two size classes from 64 KiB; at most
``max_idle_bytes`` of free blocks are kept, the rest are unmapped.

Rules (see container/intra/README.md): write only into a loan you have not
published yet; once published, your writable view is released (using it
raises ValueError) and subscribers get read-only views. A view is valid while
the message it came from is alive: keep the message, not the view.
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass

from cloneguard.container.robust import RobustMutex

MIN_BLOCK = 64 * 1024
MAX_BLOCK = 1 << 30


def size_class(nbytes: int) -> int:
    if nbytes < 0:
        raise ValueError(f"cannot loan a negative size ({nbytes})")
    if nbytes > MAX_BLOCK:
        raise ValueError(f"cannot loan {nbytes} bytes: the largest block is {MAX_BLOCK}")
    size = MIN_BLOCK
    while size < nbytes:
        size <<= 1
    return size


@dataclass
class PoolStats:
    blocks_mapped: int = 0  # blocks ever created
    loans: int = 0  # loans handed out
    reused: int = 0  # of which served from the free list
    returned: int = 0  # blocks given back by their last holder
    unmapped: int = 0  # blocks dropped because the free list was full
    repairs: int = 0  # EOWNERDEAD repairs of the pool's lock


class LoanPool:
    def __init__(self, max_idle_bytes: int = 256 << 20):
        self.max_idle_bytes = max_idle_bytes
        self._free: dict[int, list[mmap.mmap]] = {}
        self._idle_bytes = 0
        self.stats = PoolStats()
        self._mutex = RobustMutex(self._repair)

    def loan(self, nbytes: int) -> Loan:
        """A writable buffer of exactly ``nbytes`` bytes from the pool."""
        size = size_class(nbytes)
        with self._mutex:
            free = self._free.get(size)
            block = free.pop() if free else None
            if block is not None:
                self._idle_bytes -= size
                self.stats.reused += 1
            self.stats.loans += 1
        if block is None:
            # mmap(2), not malloc: the block is nobody's arena's.
            block = mmap.mmap(-1, size, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
            self.stats.blocks_mapped += 1
        return Loan(self, block, nbytes)

    def give_back(self, block: mmap.mmap) -> None:
        size = len(block)
        with self._mutex:
            self.stats.returned += 1
            if self._idle_bytes + size <= self.max_idle_bytes:
                self._free.setdefault(size, []).append(block)
                self._idle_bytes += size
                return
            self.stats.unmapped += 1
        try:
            block.close()
        except BufferError:  # someone kept a view past its message: unmapped when it goes
            pass

    @property
    def idle_bytes(self) -> int:
        return self._idle_bytes

    def _repair(self) -> None:
        # Every change under the lock is one list operation or one counter:
        # recount what the free lists hold.
        self._idle_bytes = sum(len(b) for blocks in self._free.values() for b in blocks)
        self.stats.repairs += 1


class Loan:
    """A pool block lent to one publisher, then shared read-only by every
    subscriber it is delivered to; back to the pool when the last one drops it."""

    __slots__ = ("_pool", "_block", "nbytes", "_writable", "published")

    def __init__(self, pool: LoanPool, block: mmap.mmap, nbytes: int):
        self._pool = pool
        self._block = block
        self.nbytes = nbytes
        self._writable: memoryview | None = memoryview(block)[:nbytes]
        self.published = False

    @property
    def buffer(self) -> memoryview:
        """The writable view, until the loan is published."""
        if self._writable is None:
            raise ValueError("this loan was published: its buffer is read-only now")
        return self._writable

    def seal(self) -> None:
        """Publishing: the writer's view is released; only read-only views from now."""
        if self._writable is not None:
            self._writable.release()
            self._writable = None
        self.published = True

    def view(self) -> memoryview:
        """A read-only view of the payload (valid while this loan is referenced)."""
        return memoryview(self._block)[: self.nbytes].toreadonly()

    def __del__(self) -> None:
        block, self._block = self._block, None  # type: ignore[assignment]  # the loan is being collected
        if block is None:
            return
        if self._writable is not None:
            self._writable.release()
        self._pool.give_back(block)
