"""Message faults as rules, and the fate each rule gives a message: which
are dropped, held back, duplicated or changed. Pure Python and
deterministic, no ROS: faults/messages.py applies the fates inside the
container, harness/schedule.py makes the rules.

A rule is on one topic, for the subscriptions of ``subscribers`` (their
nodes' full names; empty: every subscriber) and, where ``publishers`` is
given, only for the messages those nodes published. What it does:

``drop``       the message is never delivered
``partition``  a drop of every message from ``publishers`` to ``subscribers``
``delay``      delivered ``delay_s`` (+ up to ``jitter_s``) late
``reorder``    held until its ``window_s`` window closes, then delivered
               with the window's other messages in a shuffled order
``duplicate``  delivered twice
``corrupt``    delivered with ``fields`` set (``Corrupt`` in schedule.py)

Which messages a rule hits: with ``every`` N, the N-th, 2N-th ... message
each subscription receives on the topic; else each with ``probability``,
drawn from the rule's ``seed``, its id, the subscription and the
message's number there, so that a seed replays the same fates for the
same arrivals, whatever the timing.
"""

from __future__ import annotations

import hashlib
import json
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field

#: The engine's node (faults/messages.py) in a container the harness drives.
ENGINE_NODE_NAME = "_cloneguard_message_faults"
KINDS = ("drop", "partition", "delay", "reorder", "duplicate", "corrupt")
#: What a rule's counts call the messages it hit, by kind (beside "seen":
#: the messages it was for).
OUTCOME = {"drop": "dropped", "partition": "dropped", "delay": "delayed", "reorder": "reordered",
           "duplicate": "duplicated", "corrupt": "corrupted"}  # fmt: skip
#: A rule on every topic.
ANY_TOPIC = "*"
#: A corrupt value that sets a builtin_interfaces/Time field back by seconds.
STALE = "stale"


class RuleError(ValueError):
    """A rule that cannot be applied, and why."""


@dataclass(frozen=True)
class Rule:
    id: str
    kind: str
    topic: str
    seed: int = 0
    salt: str = ""  # what the draws depend on besides the seed (default: the id)
    probability: float = 1.0
    every: int = 0
    delay_s: float = 0.0
    jitter_s: float = 0.0
    window_s: float = 0.0
    fields: Mapping[str, object] = field(default_factory=dict)
    subscribers: tuple[str, ...] = ()
    publishers: tuple[str, ...] = ()

    def __post_init__(self):
        if self.kind not in KINDS:
            raise RuleError(f"rule {self.id}: kind must be one of {', '.join(KINDS)}, not {self.kind!r}")
        if not (self.topic.startswith("/") or self.topic == ANY_TOPIC):
            raise RuleError(f"rule {self.id}: the topic must be a full name (/scan) or '*', not {self.topic!r}")
        if not 0.0 <= self.probability <= 1.0:
            raise RuleError(f"rule {self.id}: probability must be in [0, 1], not {self.probability!r}")
        if self.every < 0:
            raise RuleError(f"rule {self.id}: every must be 0 (use probability) or a count of messages")
        if self.kind == "delay" and not (0 < self.delay_s <= 60 and 0 <= self.jitter_s <= 60):
            raise RuleError(f"rule {self.id}: a delay is 0-60 s (plus a jitter of 0-60 s)")
        if self.kind == "reorder" and not 0 < self.window_s <= 60:
            raise RuleError(f"rule {self.id}: a reorder window is 0-60 s")
        if self.kind == "corrupt" and not self.fields:
            raise RuleError(f"rule {self.id}: corrupt needs fields to set")
        if self.kind == "partition" and not (self.publishers and self.subscribers):
            raise RuleError(f"rule {self.id}: a partition needs publishers and subscribers")
        for name in (*self.subscribers, *self.publishers):
            if not name.startswith("/"):
                raise RuleError(f"rule {self.id}: nodes are named by their full names (/lidar), not {name!r}")

    @property
    def draws(self) -> str:
        """What its draws depend on besides the seed: its salt, else its id."""
        return self.salt or self.id

    def applies(self, subscriber: str, publisher: str | None) -> bool:
        """Whether the rule is for this subscriber's node and (if it names
        publishers) this message's publisher (None: not known)."""
        if self.subscribers and subscriber not in self.subscribers:
            return False
        return not self.publishers or publisher in self.publishers

    def hits(self, subscription: str, number: int) -> bool:
        """Whether the ``number``-th message (from 1) that ``subscription``
        received under this rule is one it hits."""
        if self.every:
            return number % self.every == 0
        return self.probability >= 1.0 or unit(self.seed, self.draws, subscription, number) < self.probability

    def to_json(self) -> dict:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["fields"] = {k: _json_value(v) for k, v in self.fields.items()}
        d["subscribers"], d["publishers"] = list(self.subscribers), list(self.publishers)
        return d

    @classmethod
    def from_json(cls, d: Mapping) -> Rule:
        known = set(cls.__dataclass_fields__)
        unknown = set(d) - known
        if unknown:
            raise RuleError(f"unknown rule field(s): {', '.join(sorted(unknown))}")
        try:
            values = dict(d)
            values["fields"] = {k: _from_json_value(v) for k, v in dict(d.get("fields", {})).items()}
            values["subscribers"] = tuple(d.get("subscribers", ()))
            values["publishers"] = tuple(d.get("publishers", ()))
            return cls(**values)
        except TypeError as exc:
            raise RuleError(f"a rule needs id, kind and topic: {exc}") from None


def rules_from_text(text: str) -> list[Rule]:
    """The rules of a JSON list (the engine's ``faults`` parameter)."""
    try:
        items = json.loads(text or "[]")
    except json.JSONDecodeError as exc:
        raise RuleError(f"not JSON: {exc}") from None
    if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
        raise RuleError("expected a JSON list of rule objects")
    rules = [Rule.from_json(i) for i in items]
    ids = [r.id for r in rules]
    if len(set(ids)) != len(ids):
        raise RuleError("two rules have the same id")
    return rules


def rules_to_text(rules: list[Rule]) -> str:
    return json.dumps([r.to_json() for r in rules])


def unit(seed: int, rule_id: str, subscription: str, number: int) -> float:
    """A number in [0, 1) that depends only on its arguments."""
    digest = hashlib.blake2b(f"{seed}|{rule_id}|{subscription}|{number}".encode(), digest_size=8).digest()
    return struct.unpack("<Q", digest)[0] / 2.0**64


# Floats JSON cannot carry (NaN, ±inf) travel as strings.
_SPECIAL = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


def _json_value(v: object) -> object:
    if isinstance(v, float) and not math.isfinite(v):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf")
    return v


def _from_json_value(v: object) -> object:
    if isinstance(v, list):  # (STALE, s) came as a list
        return tuple(v)
    return _SPECIAL.get(v, v) if isinstance(v, str) else v


@dataclass
class Fate:
    """What becomes of one message: ``drop`` it, or deliver it ``copies``
    times, at ``due`` (monotonic s; 0: now), with ``corrupt`` fields set;
    messages due at once go in ``order`` (a reorder window's shuffle);
    ``hit`` the rules that hit it."""

    drop: bool = False
    copies: int = 1
    due: float = 0.0
    order: float = 0.0
    corrupt: dict[str, object] = field(default_factory=dict)
    hit: list[Rule] = field(default_factory=list)


def fate(
    rules: list[Rule], subscription: str, subscriber: str, publisher: str | None, counts: dict, now: float
) -> Fate:
    """The fate of the next message ``subscription`` (of node
    ``subscriber``) received from ``publisher``, under ``rules`` (the
    topic's); ``counts`` keeps each (rule, subscription)'s message number."""
    out = Fate()
    for rule in rules:
        if not rule.applies(subscriber, publisher):
            continue
        key = (rule.id, subscription)
        number = counts[key] = counts.get(key, 0) + 1
        if not rule.hits(subscription, number):
            continue
        out.hit.append(rule)
        if rule.kind in ("drop", "partition"):
            out.drop = True
            return out
        if rule.kind == "duplicate":
            out.copies += 1
        elif rule.kind == "corrupt":
            out.corrupt.update(rule.fields)
        elif rule.kind == "delay":
            extra = rule.jitter_s * unit(rule.seed, rule.draws + "/jitter", subscription, number)
            out.due = max(out.due, now + rule.delay_s + extra)
        elif rule.kind == "reorder":
            # Every message of a window is due when it closes; then they go
            # in an order drawn like a hit, so a seed replays it too.
            out.due = max(out.due, (math.floor(now / rule.window_s) + 1) * rule.window_s)
            out.order = unit(rule.seed, rule.draws + "/order", subscription, number)
    return out


def corrupt(msg, fields: Mapping[str, object]):
    """Set ``fields`` (dotted paths) of ``msg`` in place: a number to a
    number field, or to every element of a sequence of numbers;
    ``(STALE, s)`` moves a builtin_interfaces/Time back by s seconds.
    A path the message does not have is a RuleError."""
    for path, value in fields.items():
        *parents, name = path.split(".")
        target = msg
        for part in parents:
            target = _field(target, part, path)
        current = _field(target, name, path)
        if isinstance(value, (list, tuple)) and len(value) == 2 and value[0] == STALE:
            ns = int(current.sec) * 1_000_000_000 + int(current.nanosec) - int(float(value[1]) * 1e9)
            ns = max(ns, 0)
            current.sec, current.nanosec = ns // 1_000_000_000, ns % 1_000_000_000
        elif hasattr(current, "__len__") and not isinstance(current, (str, bytes)):
            cast = _cast(current[0]) if len(current) else _cast(value)
            setattr(target, name, [cast(value)] * len(current))
        else:
            setattr(target, name, _cast(current)(value))
    return msg


def _cast(like: object):
    """The conversion a value needs to go into a field holding ``like``
    (rclpy's setters take no int for a float field)."""
    for kind in (bool, int, float):
        if isinstance(like, kind):
            return kind
    return lambda v: v


def _field(obj, name: str, path: str):
    if name not in getattr(obj, "get_fields_and_field_types", dict)():
        raise RuleError(f"{type(obj).__name__} has no field {name!r} (in {path!r})")
    return getattr(obj, name)
