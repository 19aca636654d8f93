"""What was sent on a topic and what a subscriber inside the container
heard, message by message: the rig's way to measure message faults from
outside (tests/test_message_faults.py, scenarios/test_message_faults.py).

A ``cloneguard::Talker`` publishes "m <n>" on /chatter every ``period_s``
and the rig's ``faults::MessageProbe`` republishes what it hears on
/message_probe/heard; the harness subscribes to both. The rig's own, not
the public test API.
"""

from __future__ import annotations

import bisect
from typing import TYPE_CHECKING

from std_msgs.msg import String

from cloneguard.faults import PACKAGE as RIG

from .system import NodeSpec

if TYPE_CHECKING:
    from .client import Received, Recorder
    from .pytest_plugin import SystemFactory

#: Container arguments per profile (the rig's scenarios' names).
PROFILE_ARGS = {"threads": [], "shared": ["--isolated", "--profile", "shared"],
                "per-node": ["--isolated", "--profile", "per-node"]}  # fmt: skip
TOPIC = "/chatter"
#: 20 more messages after a fault (0.4 s at 50 Hz) outlast any delay or
#: reorder window the rig sets (at most 0.3 s).
SETTLE_MESSAGES = 20


class ChatterProbe:
    """The system, and what was sent and heard on it."""

    def __init__(
        self, system_factory: SystemFactory, profile: str = "shared", intra: bool = False, period_s: float = 0.02
    ):
        extra = {"use_intra_process_comms": True} if intra else {}
        talker = {"topic": TOPIC, "period": period_s, "message": "m"}
        nodes = [
            NodeSpec("cloneguard", "cloneguard::Talker", parameters=talker, extra_arguments=extra),
            NodeSpec(RIG, "faults::MessageProbe", parameters={"topic": TOPIC}, extra_arguments=extra),
        ]
        self.system = system_factory(nodes, PROFILE_ARGS[profile])
        self.sent = self.system.topic(String, TOPIC, qos=1000)
        self.heard = self.system.topic(String, "/message_probe/heard", qos=1000)
        self.heard.wait_count(5, timeout=15)

    def _now(self, rec: Recorder, since: int = 0) -> list[Received]:
        """What ``rec`` got, from its ``since``-th message on, from the
        container now running: after a restart the Talker counts from 0
        again, and the recorders hold the old one's numbers too."""
        items = rec.items()
        return items[max(since, self._first_now(items)) :]

    def _first_now(self, items: list[Received]) -> int:
        """The index of the first of ``items`` the container now running
        sent (a recorder appends in the order it gets, at_ns rising)."""
        return bisect.bisect_left(items, self.system.started_ns, key=lambda r: r.at_ns)

    def settle(self) -> int:
        """Let SETTLE_MESSAGES more go and every one of them be heard; the
        last number sent."""
        self.sent.wait_count(len(self.sent) + SETTLE_MESSAGES, timeout=10)
        last = max(self.sent_numbers())
        since = self._first_now(self.heard.items())  # not the old container's higher numbers
        self.heard.wait_for(lambda msg: number(msg) >= last, timeout=10, what=f"m {last} heard", since=since)
        return last

    def sent_numbers(self) -> list[int]:
        return [number(r.msg) for r in self._now(self.sent)]

    def heard_items(self, since: int = 0) -> list[Received]:
        """Each heard (``.msg``, ``.at_ns``), from the ``since``-th on."""
        return self._now(self.heard, since)

    def heard_numbers(self, since: int = 0) -> list[int]:
        """In the order heard, from the ``since``-th message heard on."""
        return [number(r.msg) for r in self.heard_items(since)]

    def sent_at(self) -> dict[int, int]:
        """Number -> when the harness got it as sent (monotonic ns)."""
        return {number(r.msg): r.at_ns for r in self._now(self.sent)}

    def missing(self) -> list[int]:
        """Sent while the probe listened, never heard (after settle()), in
        the container now running."""
        last = self.settle()
        heard = self.heard_numbers()
        return sorted(set(range(min(heard), last + 1)) - set(heard))


def number(msg: String) -> int:
    return int(msg.data.split()[-1])
