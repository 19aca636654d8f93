"""Fast DDS's infinite participant-listener wait, made finite waits that
sleep (listenerwait.c: why, and what it assumes).

Installed once per container process, at the isolated host's start-up,
before any participant is deleted. Where it cannot be (another Fast DDS than
it was measured on), the container says so and goes on: a participant
deletion can then spin as it does upstream (eProsima/Fast-DDS#6513)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from cloneguard.container.isolated._clonecore import ffi, lib

if TYPE_CHECKING:
    from typing import Protocol

    class _Log(Protocol):
        """What ``bound`` says a failed check on: rclpy's logger, or logging's."""

        def warning(self, message: str, /) -> object: ...


WHY_SIZE = 256


def bound(log: _Log) -> bool:
    """Install it; True when installed (or already), False when libfastrtps
    is not loaded (another RMW: nothing to do) or a check failed (said on
    ``log``)."""
    why = ffi.new("char[]", WHY_SIZE)
    rc = lib.cg_bound_listener_wait(why, WHY_SIZE)
    if rc < 0:
        log.warning(
            "a DDS participant's deletion can spin for ever here (eProsima/Fast-DDS#6513): "
            f"its listener wait is not bounded: {ffi.string(why).decode(errors='replace')}"
        )
    return rc > 0


def waits_bounded() -> int | None:
    """How many infinite waits the bounded one has served; None when
    libfastrtps does not call it (now)."""
    n = lib.cg_listener_waits_bounded()
    return None if n < 0 else int(n)
