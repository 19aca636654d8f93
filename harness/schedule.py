"""Fault schedules: which faults a System gets, and when, as data (the way
Jepsen describes its nemesis): one fault, a sequence, or faults drawn at
random over a window from a trial's Random, so that a trial replays.

    from cloneguard.harness.schedule import At, Freeze, Kill, KillAt, Starve, random_over, sequence

    robot.inject([At(0.2, Freeze("/planner", 1.0)), At(0.5, Kill("/odometry"))])
    robot.inject(sequence(Starve("/planner", 0.01, 2.0), Kill("/planner"), every_s=0.5))
    robot.inject(random_over(t.rng, 3.0, [Kill("/planner"), Freeze("/map_server", 0.5)], count=2))
    robot.inject(KillAt("/planner", "python-lock"))
    robot.inject([At(0.0, Drop("/scan", 4.0, probability=0.5)), At(1.0, Delay("/odom", 2.0, delay_s=0.3))])

``inject`` also takes a single fault or ``At``, and a bare fault in a list
runs at once (at 0 s). Faults run at their times from the schedule's start; a freeze, a
starvation or a message fault (message_faults.py: ``Drop``, ``Delay``,
``Reorder``, ``Duplicate``, ``Corrupt``, ``Partition``) lasts its seconds
on a thread of its own, so faults overlap
where their times do. Each is recorded in ``System.faults`` (and so in
the trial's history in the report) when it ends.

Public and kept stable, like system.py.
"""

from __future__ import annotations

import random
import signal
import threading
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from .message_faults import Corrupt, Delay, Drop, Duplicate, MessageFault, Partition, Reorder, stale

__all__ = [
    "At", "Corrupt", "Delay", "Drop", "Duplicate", "Freeze", "Kill", "KillAt", "MessageFault", "Partition",
    "Reorder", "Starve", "as_schedule", "random_over", "run_schedule", "sequence", "stale",
]  # fmt: skip

if TYPE_CHECKING:
    from .system import Fault, System


@dataclass(frozen=True)
class Kill:
    """A signal to the node's process (SIGKILL unless ``sig``)."""

    node: str
    sig: int = signal.SIGKILL
    lasts = False

    def apply(self, system: System) -> None:
        system.kill(self.node, self.sig)


@dataclass(frozen=True)
class KillAt:
    """SIGKILL to the node's process at a place in its own code
    (``allocation``, ``python-allocation``, ``python-lock``: stops.py), at
    its ``after``-th pass from the fault's time; at ``python-lock``,
    ``lock`` may name the one lock it dies holding."""

    node: str
    place: str
    after: int = 1
    lock: str = ""
    lasts = False

    def apply(self, system: System) -> None:
        system.kill_at(self.node, self.place, after=self.after, lock=self.lock)


@dataclass(frozen=True)
class Freeze:
    """The node's process stopped for ``seconds`` (SIGSTOP, then SIGCONT)."""

    node: str
    seconds: float
    lasts = True

    def apply(self, system: System) -> None:
        system.freeze(self.node, self.seconds)


@dataclass(frozen=True)
class Starve:
    """The node's process held to ``cpus`` CPUs for ``seconds``."""

    node: str
    cpus: float
    seconds: float
    lasts = True

    def apply(self, system: System) -> None:
        system.starve(self.node, self.cpus, self.seconds)


ScheduledFault = Kill | KillAt | Freeze | Starve | MessageFault
FAULTS = (Kill, KillAt, Freeze, Starve, MessageFault)


@dataclass(frozen=True)
class At:
    """``fault`` at ``seconds`` after the schedule starts."""

    seconds: float
    fault: ScheduledFault

    def __post_init__(self) -> None:
        if not 0 <= self.seconds <= 3600:
            raise ValueError(f"a fault's time is 0-3600 s from the schedule's start, not {self.seconds!r}")


def sequence(*faults: ScheduledFault, every_s: float, first_s: float = 0.0) -> list[At]:
    """The faults one after another, ``every_s`` apart, from ``first_s``."""
    return [At(first_s + i * every_s, f) for i, f in enumerate(faults)]


def random_over(rng: random.Random, window_s: float, faults: Sequence[ScheduledFault], count: int = 1) -> list[At]:
    """``count`` faults, each drawn from ``faults``, at instants drawn over
    the first ``window_s`` seconds: from ``rng`` (a trial's ``t.rng``)."""
    if not faults:
        raise ValueError("random_over needs faults to draw from")
    return sorted((At(rng.uniform(0.0, window_s), rng.choice(list(faults))) for _ in range(count)),
                  key=lambda a: a.seconds)  # fmt: skip


def as_schedule(schedule: At | ScheduledFault | Iterable[At | ScheduledFault]) -> list[At]:
    """A schedule from what ``System.inject`` takes: an ``At``, a fault (at
    once), or a list of those; anything else is refused, saying what."""
    items = [schedule] if isinstance(schedule, (At, *FAULTS)) else list(schedule)
    out = []
    for item in items:
        if isinstance(item, At):
            out.append(item)
        elif isinstance(item, FAULTS):
            out.append(At(0.0, item))
        else:
            raise TypeError(
                f"a schedule holds At(seconds, fault) or faults ({', '.join(f.__name__ for f in FAULTS)}), "
                f"not {type(item).__name__}"
            )
    return sorted(out, key=lambda a: a.seconds)


def run_schedule(system: System, schedule: At | ScheduledFault | Iterable[At | ScheduledFault]) -> list[Fault]:
    """Run ``schedule`` on ``system``; the System faults it recorded."""
    items = as_schedule(schedule)
    first = len(system.faults)
    errors: list[BaseException] = []

    def lasting(fault: ScheduledFault) -> None:
        try:
            fault.apply(system)
        except BaseException as exc:  # raised once every fault has ended
            errors.append(exc)

    start = time.monotonic()
    threads = []
    for at in items:
        time.sleep(max(0.0, start + at.seconds - time.monotonic()))
        if at.fault.lasts:
            thread = threading.Thread(target=lasting, args=(at.fault,), name=f"fault-{at.fault.node}")
            thread.start()
            threads.append(thread)
        else:
            lasting(at.fault)
    for thread in threads:
        thread.join()
    if errors:
        raise errors[0]
    return system.faults[first:]
