"""Wakers: a container thread per subscriber node process that triggers its
intra-process subscriptions' guard conditions for the publishers.

Why (waker.c says it in full): triggering a guard condition locks the
subscriber's wait-set mutex, a plain std::mutex; a publisher killed there
would leave the subscriber's executor stuck for good. A publisher posts to
the subscriber's waker instead (lock-free); the waker, which can only die
with the container, does the trigger.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._rclglue import ffi, lib

if TYPE_CHECKING:
    from rclpy.guard_condition import GuardCondition

CLOSE_TIMEOUT_MS = 1000


class Waker:
    def __init__(self) -> None:
        out = ffi.new("struct cgw_waker **")
        rc = lib.cgw_new(out)
        if rc < 0:
            raise OSError(-rc, "cannot start an intra-process waker thread")
        self._w = out[0]
        self._closed = False

    def add(self, guard_condition: GuardCondition) -> int:
        """A token for ``guard_condition`` (an rclpy GuardCondition)."""
        with guard_condition.handle:
            token = lib.cgw_add(self._w, ffi.cast("void *", guard_condition.handle.pointer))
        if token < 0:
            raise OSError(-token, f"intra-process waker: no room for another subscription ({lib.CGW_TOKENS} per node)")
        return token

    def remove(self, token: int) -> None:
        """After this, the token's guard condition is never touched again.
        After close() it does nothing: the block may be another waker's now."""
        if not self._closed:
            lib.cgw_remove(self._w, token)

    def post(self, token: int) -> None:
        lib.cgw_post(self._w, token)

    def close(self) -> bool:
        """Stop the thread; False when it is stuck (in a dead subscriber's
        lock) and was left behind. Posts through it stay harmless afterwards
        (waker.c keeps every block)."""
        self._closed = True
        return lib.cgw_close(self._w, CLOSE_TIMEOUT_MS) == 0
