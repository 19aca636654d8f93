"""Faults on the messages between nodes, as schedule entries beside
``Kill`` and ``Freeze`` (schedule.py), with no node changed:

    from cloneguard.harness.schedule import At, Corrupt, Delay, Drop, Partition

    robot.inject([
        At(0.0, Drop("/scan", 4.0, probability=0.5)),
        At(1.0, Delay("/odom", 3.0, delay_s=0.3)),
        At(2.0, Corrupt("/scan", 1.0, fields={"ranges": math.nan})),
        At(3.0, Partition(publishers=["/lidar"], subscribers=["/planner"], seconds=2.0)),
    ])

Each lasts ``seconds`` and hits, on its topic (``"*"``: every topic), the
messages received by the nodes of ``subscribers`` (all, if empty) from the
nodes of ``publishers`` (any, if empty): all of them, each with
``probability``, or every ``every``-th. The rig's engine does it inside the
container (faults/messages.py: loaded at a System's first message fault as
the node ``/_cloneguard_message_faults``), over DDS and intra-process
alike; which messages a fault hits is drawn from ``seed`` (else the
trial's seed: ``System.seed``), so a seed replays them. Each is recorded in
``System.faults`` with ``counts``: how many messages it dropped, delayed,
reordered, duplicated or corrupted.

Public and kept stable, like schedule.py.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import KW_ONLY, dataclass, field
from typing import TYPE_CHECKING, ClassVar

from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from std_srvs.srv import Trigger

from cloneguard.faults import PACKAGE as RIG_PACKAGE
from cloneguard.faults.message_rules import ENGINE_NODE_NAME, OUTCOME, STALE, Rule, rules_to_text

__all__ = ["Corrupt", "Delay", "Drop", "Duplicate", "MessageFault", "Partition", "Reorder", "stale"]

if TYPE_CHECKING:
    from .client import ContainerClient
    from .system import System


def stale(seconds: float) -> tuple[str, float]:
    """A ``Corrupt`` value: the time field set ``seconds`` into the past."""
    return (STALE, float(seconds))


@dataclass(frozen=True)
class MessageFault:
    """What every message fault has: its topic, how long it lasts, whose
    messages it hits and how many of them."""

    topic: str
    seconds: float
    _: KW_ONLY
    probability: float = 1.0
    every: int = 0
    subscribers: Sequence[str] = ()  # kept as a tuple
    publishers: Sequence[str] = ()  # kept as a tuple
    seed: int | None = None
    kind: ClassVar[str] = ""
    lasts: ClassVar[bool] = True

    def __post_init__(self) -> None:
        if not 0 < self.seconds <= 3600:
            raise ValueError(f"a message fault lasts 0-3600 s, not {self.seconds!r}")
        # Lists are welcome: kept as tuples (the fault is frozen).
        object.__setattr__(self, "subscribers", tuple(self.subscribers))
        object.__setattr__(self, "publishers", tuple(self.publishers))
        self.rule("check", 0)  # what the engine would refuse, refused now

    @property
    def node(self) -> str:
        """What ``System.faults`` files it under: its topic."""
        return self.topic

    def _extra(self) -> dict:
        return {}

    def rule(self, rule_id: str, seed: int) -> Rule:
        return Rule(
            id=rule_id,
            kind=self.kind,
            topic=self.topic,
            seed=seed,
            salt=self.describe(),  # the same fault draws alike in every run, whatever its id
            probability=self.probability,
            every=self.every,
            subscribers=tuple(self.subscribers),
            publishers=tuple(self.publishers),
            **self._extra(),
        )

    def describe(self) -> str:
        share = f"every {self.every}th" if self.every else f"{self.probability:.0%}"
        parts = [f"{self.kind} {share} on {self.topic}", *self._details()]
        if self.publishers:
            parts.append(f"from {', '.join(self.publishers)}")
        if self.subscribers:
            parts.append(f"to {', '.join(self.subscribers)}")
        return " ".join(parts) + f" for {self.seconds:g} s"

    def _details(self) -> list[str]:
        return []

    def apply(self, system: System) -> None:
        system.message_fault(self)


@dataclass(frozen=True)
class Drop(MessageFault):
    """The messages it hits are never delivered."""

    kind: ClassVar[str] = "drop"


@dataclass(frozen=True)
class Delay(MessageFault):
    """Delivered ``delay_s`` late (plus up to ``jitter_s``, drawn per message)."""

    delay_s: float = 0.1
    jitter_s: float = 0.0
    kind: ClassVar[str] = "delay"

    def _extra(self) -> dict:
        return {"delay_s": self.delay_s, "jitter_s": self.jitter_s}

    def _details(self) -> list[str]:
        return [f"by {self.delay_s * 1e3:g} ms" + (f" + up to {self.jitter_s * 1e3:g} ms" if self.jitter_s else "")]


@dataclass(frozen=True)
class Reorder(MessageFault):
    """Held until its ``window_s`` window closes, then delivered with the
    window's others in a shuffled order."""

    window_s: float = 0.1
    kind: ClassVar[str] = "reorder"

    def _extra(self) -> dict:
        return {"window_s": self.window_s}

    def _details(self) -> list[str]:
        return [f"within {self.window_s * 1e3:g} ms windows"]


@dataclass(frozen=True)
class Duplicate(MessageFault):
    """Delivered twice."""

    kind: ClassVar[str] = "duplicate"


@dataclass(frozen=True)
class Corrupt(MessageFault):
    """Delivered with ``fields`` set: a dotted path (``header.stamp``,
    ``pose.pose.position.x``, ``ranges``) to a number (``math.nan``,
    ``math.inf``, ``0``, out of range: any), set on every element of a
    sequence; ``stale(s)`` moves a time ``s`` seconds back."""

    fields: dict = field(default_factory=dict)
    kind: ClassVar[str] = "corrupt"

    def _extra(self) -> dict:
        return {"fields": dict(self.fields)}

    def _details(self) -> list[str]:
        def shown(v: object) -> str:
            if isinstance(v, tuple) and v and v[0] == STALE:
                return f"{v[1]:g} s stale"
            return "NaN" if isinstance(v, float) and math.isnan(v) else repr(v)

        return ["setting " + ", ".join(f"{k}={shown(v)}" for k, v in self.fields.items())]


@dataclass(frozen=True)
class Partition(MessageFault):
    """The nodes of ``subscribers`` hear nothing the nodes of ``publishers``
    publish (on ``topic``; every topic by default), then hear them again."""

    topic: str = "*"
    seconds: float = 1.0
    kind: ClassVar[str] = "partition"


class MessageEngine:
    """The harness's side of the rig's engine in one container: loads it,
    sets the rules in force (the faults under way), reads what each did."""

    def __init__(self, client: ContainerClient):
        self._client = client
        self._lock = threading.Lock()
        self._rules: dict[str, Rule] = {}
        self._next = 0
        resp = client.load(RIG_PACKAGE, "faults::MessageFaults", node_name=ENGINE_NODE_NAME)
        if not resp.success:
            raise RuntimeError(f"the message-fault engine did not load: {resp.error_message}")
        self.unique_id = resp.unique_id
        self._set = client.service_client(SetParameters, f"/{ENGINE_NODE_NAME}/set_parameters")
        self._counts = client.service_client(Trigger, f"/{ENGINE_NODE_NAME}/counts")

    def start(self, fault: MessageFault, seed: int) -> str:
        """Put ``fault`` in force; its rule's id."""
        with self._lock:
            self._next += 1
            rule_id = f"m{self._next}"
            self._rules[rule_id] = fault.rule(rule_id, seed)
            self._send()
        return rule_id

    def stop(self, rule_id: str) -> dict[str, int]:
        """End it; what it did."""
        with self._lock:
            rule = self._rules.pop(rule_id)
            self._send()
        answer = self._client.call(self._counts, Trigger.Request(), resend_after=1.0)
        # Every fault's own two counts, 0 if it met nothing, and any other
        # it made ("not corrupted: ..." with the reason, "passed: ...").
        return {"seen": 0, OUTCOME[rule.kind]: 0, **json.loads(answer.message).get(rule_id, {})}

    def _send(self) -> None:
        text = rules_to_text(list(self._rules.values()))
        value = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=text)
        request = SetParameters.Request(parameters=[Parameter(name="faults", value=value)])
        # Setting the whole list again is harmless: it may be resent.
        [result] = self._client.call(self._set, request, resend_after=1.0).results
        if not result.successful:
            raise ValueError(f"the message-fault engine refused the faults: {result.reason}")


def run_message_fault(engine: MessageEngine, fault: MessageFault, seed: int) -> tuple[int, int, dict[str, int]]:
    """``fault`` in force for its seconds; (start_ns, end_ns, counts)."""
    start = time.monotonic_ns()
    rule_id = engine.start(fault, seed)
    try:
        time.sleep(fault.seconds)
    finally:
        end = time.monotonic_ns()
        counts = engine.stop(rule_id)
    return start, end, counts
