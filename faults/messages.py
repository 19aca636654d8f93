"""Message faults inside a container, with no node changed: the engine.

``faults::MessageFaults`` is a component of the test rig. Loaded into a
container (the harness does it at the first message fault of a System),
it puts the engine between every subscription of the container's one
interpreter and its callback: rclpy's executor's take of a DDS message
(``Executor._take_subscription``, whatever executor spins the node, in
every mode and profile: every node process runs in that interpreter), and
the delivery of an intra-process subscription (``intra.api.Subscription``).
Until a rule is set on a topic, a take on it costs one dict lookup more;
a container without this component loaded is not touched at all, and a
container installed without the rig cannot load it.

The rules (message_rules.py) are the node's ``faults`` parameter, a JSON
list, set through ROS's own parameter service: every set replaces them all,
and a bad list is refused, saying why, changing nothing. The counts of what
each rule did (``seen``: the messages it was for; ``dropped``, ``delayed``
...: those it hit) are on the ``~/counts`` service (std_srvs/Trigger: JSON).

A message held back (delay, reorder) is delivered by its subscriber's own
executor, as any message is, through a steady-clock timer the engine makes
on that subscriber's node and sets to the earliest due time (``_Holder``).

A rule that names publishers needs each message's publisher: over DDS
the engine reads its gid (container/intra/dds_reader.py's take) and finds
its node in the ROS graph; an intra-process message's publisher is noted
when it hands the message over (``Publisher._hand_over``), while such a
rule is on its topic. A message whose publisher is not known passes such a
rule, counted (``passed: publisher not known``).
"""

from __future__ import annotations

import copy
import heapq
import importlib
import itertools
import json
import math
import statistics
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass

from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.executors import Executor, await_or_execute
from rclpy.node import Node
from rclpy.serialization import deserialize_message
from rclpy.subscription import Subscription
from rclpy.timer import Timer
from std_srvs.srv import Trigger

from cloneguard.container.intra import api as intra_api
from cloneguard.container.intra.dds_reader import TakeBuffer

from .message_rules import ANY_TOPIC, ENGINE_NODE_NAME, OUTCOME, Fate, Rule, RuleError, corrupt, fate, rules_from_text


@dataclass
class _Held:
    """A message held back for its subscriber: ``deliver()`` does it."""

    due: float  # time.monotonic()
    order: float  # among those due at once (a reorder window's shuffle)
    deliver: Callable[[], None]


#: How many of a holder's last timer wake-ups its lead is the median of.
LEAD_SAMPLES = 15


class _Holder:
    """One subscriber node's held messages, delivered by its own executor:
    a steady-clock timer of the node's, set to the earliest due time (rcl's
    wait wakes for it with no Python thread on the way), delivers what is
    due and sets itself to the next. Used only by that node's executor.

    The executor runs a timer's callback some time after the timer's time
    (rcl's wake-up, then a turn of the executor: 0.4-1.5 ms on this
    project's machine), and that would add to every delay. So the timer is
    set that much ahead (its *lead*: the median of how late its last
    LEAD_SAMPLES wake-ups were, measured here), and what is due within the
    lead when it fires is delivered then: the subscriber gets each held
    message at its due time give or take the wake-up's jitter."""

    def __init__(self, node):
        self._node = node
        self._heap: list[tuple[float, int, _Held]] = []
        self._seq = itertools.count()
        self._timer: Timer | None = None
        self._armed = math.inf  # the due time the timer is set for
        self._wake_at = 0.0  # when the timer was set to fire (time.monotonic())
        self._late: deque[float] = deque(maxlen=LEAD_SAMPLES)  # its last wake-ups, s after _wake_at

    def lead(self) -> float:
        return statistics.median(self._late) if self._late else 0.0

    def hold(self, held: _Held) -> None:
        heapq.heappush(self._heap, (held.due, next(self._seq), held))
        if held.due < self._armed:
            self._arm()

    def _arm(self) -> None:
        due = self._heap[0][0]
        now = time.monotonic()
        period = max(due - self.lead() - now, 1e-6)
        if self._timer is None:
            self._timer = self._node.create_timer(period, self._fire, clock=_STEADY)
        else:
            self._timer.timer_period_ns = int(period * 1e9)
            self._timer.reset()
        self._armed = due
        self._wake_at = now + period

    def _fire(self) -> None:
        now = time.monotonic()
        self._late.append(max(0.0, now - self._wake_at))
        due = []
        within = now + self.lead()
        while self._heap and self._heap[0][0] <= within:
            due.append(heapq.heappop(self._heap)[2])
        for held in sorted(due, key=lambda h: (h.due, h.order)):
            held.deliver()
        if self._heap:
            self._arm()
        else:
            assert self._timer is not None
            self._timer.cancel()
            self._armed = math.inf


class _Engine:
    """The rules in force, what each did, and the messages held back. One
    per interpreter (``ENGINE``); the rule tables are replaced whole, never
    changed in place, so a take reads them without a lock. What a
    subscription changes (its message numbers, its counts, its held
    messages) is its own: only its executor writes it."""

    def __init__(self):
        self.by_topic: dict[str, list[Rule]] = {}
        self.any_topic: list[Rule] = []
        self._counts: dict[tuple[str, str], Counter] = {}  # (rule id, subscription) -> counts
        self._numbers: dict = {}  # (rule id, subscription) -> messages seen
        self._holders: dict[int, _Holder] = {}  # id(node) -> its held messages
        self._publishers: dict[bytes, str] = {}  # gid -> node full name
        self._buffers: dict[int, TakeBuffer] = {}  # per subscription (its process takes with it)
        self.installed = False

    # -- the rules ---------------------------------------------------------------------------

    def set_rules(self, rules: list[Rule]) -> None:
        every = [r for r in rules if r.topic == ANY_TOPIC]
        by_topic: dict[str, list[Rule]] = {}
        for rule in rules:
            if rule.topic != ANY_TOPIC:
                by_topic.setdefault(rule.topic, []).append(rule)
        for topic_rules in by_topic.values():
            topic_rules.extend(every)
        self.by_topic, self.any_topic = by_topic, every

    def rules_for(self, topic: str) -> list[Rule] | None:
        """The rules on ``topic`` (those on every topic included); None: none."""
        return self.by_topic.get(topic) or self.any_topic or None

    def counts(self) -> dict[str, dict[str, int]]:
        """Rule id -> what it did, over every subscription."""
        out: dict[str, Counter] = {}
        for (rule_id, _), counts in list(self._counts.items()):
            out.setdefault(rule_id, Counter()).update(counts)
        return {rule_id: dict(c) for rule_id, c in out.items()}

    def _count(self, rule: Rule, subscription: str, what: str) -> None:
        self._counts.setdefault((rule.id, subscription), Counter())[what] += 1

    # -- a message's fate ----------------------------------------------------------------------

    def apply(self, rules, subscription: str, subscriber: str, publisher, node, msg_args: tuple, deliver, *,
              shared: bool = False):  # fmt: skip
        """Decide the fate of one message and carry it out: the callable
        that delivers it now (``deliver(msg_args)``, for the executor), or
        None (dropped, or held to be delivered later). ``shared``: the
        message is others' too (intra-process): corrupt a copy."""
        f: Fate = fate(rules, subscription, subscriber, publisher, self._numbers, time.monotonic())
        self._count_seen(rules, subscription, subscriber, publisher)
        if f.corrupt and not f.drop:
            msg_args = self._corrupted(f, subscription, msg_args, shared)
        for rule in f.hit:
            if rule.kind != "corrupt" or f.corrupt:  # emptied when it could not be done
                self._count(rule, subscription, OUTCOME[rule.kind])
        if f.drop:
            return None
        copies = f.copies

        def run():
            for _ in range(copies):
                deliver(msg_args)

        if f.due:
            holder = self._holders.get(id(node))
            if holder is None:
                holder = self._holders[id(node)] = _Holder(node)
            holder.hold(_Held(f.due, f.order, run))
            return None
        return run

    def _count_seen(self, rules, subscription: str, subscriber: str, publisher) -> None:
        for rule in rules:
            if rule.applies(subscriber, publisher):
                self._count(rule, subscription, "seen")
            elif publisher is None and rule.publishers and (not rule.subscribers or subscriber in rule.subscribers):
                self._count(rule, subscription, "passed: publisher not known")

    def _corrupted(self, f: Fate, subscription: str, msg_args: tuple, shared: bool) -> tuple:
        """The message with ``f.corrupt``'s fields set (a copy if others
        have it too); if it cannot be (a field it has not), the message as
        it was, ``f.corrupt`` emptied and the reason counted."""
        msg = msg_args[0]
        if shared:
            msg = msg.to_message() if hasattr(msg, "to_message") else copy.deepcopy(msg)
        try:
            return (corrupt(msg, f.corrupt), *msg_args[1:])
        except (RuleError, TypeError, ValueError, AttributeError) as exc:
            f.corrupt = {}
            for rule in f.hit:
                if rule.kind == "corrupt":
                    self._count(rule, subscription, f"not corrupted: {exc}")
            return msg_args

    # -- publishers over DDS -----------------------------------------------------------------

    def publisher_name(self, node, topic: str, gid: bytes) -> str | None:
        name = self._publishers.get(gid)
        if name is None:
            for info in node.get_publishers_info_by_topic(topic):
                ns = info.node_namespace.rstrip("/")
                self._publishers[bytes(info.endpoint_gid[: len(gid)])] = f"{ns}/{info.node_name}"
            name = self._publishers.get(gid)
        return name

    def buffer(self, sub) -> TakeBuffer:
        buf = self._buffers.get(id(sub))
        if buf is None:
            buf = self._buffers[id(sub)] = TakeBuffer()
        return buf


_STEADY = Clock(clock_type=ClockType.STEADY_TIME)  # time.monotonic()'s clock


ENGINE = _Engine()

# -- the two places messages reach callbacks -------------------------------------------------------

_take_subscription = Executor._take_subscription
_intra_deliver = intra_api.Subscription._deliver
_intra_hand_over = intra_api.Publisher._hand_over
#: Intra-process messages handed over while a rule on their topic names
#: publishers: id -> (the message, kept so that its id is not reused while
#: here; its publisher's node). The newest INTRA_SOURCES only.
_intra_sources: OrderedDict[int, tuple[object, str]] = OrderedDict()
INTRA_SOURCES = 4096


def _node_of(executor: Executor, sub: Subscription):
    for node in executor.get_nodes():
        if sub in node.subscriptions:
            return node
    return None


def _faulty_take_subscription(self: Executor, sub: Subscription):
    rules = ENGINE.rules_for(sub.topic_name)
    if rules is None:
        return _take_subscription(self, sub)
    node = _node_of(self, sub)
    if node is None:
        return _take_subscription(self, sub)
    subscriber = node.get_fully_qualified_name()
    publisher = None
    with_info = sub._callback_type is not Subscription.CallbackType.MessageOnly
    if any(r.publishers for r in rules) and not with_info:
        with sub.handle:
            taken = ENGINE.buffer(sub).take(sub.handle.pointer)
        if taken is None:
            return None
        data, gid = taken
        publisher = ENGINE.publisher_name(node, sub.topic_name, gid)
        args: tuple = (data if sub.raw else deserialize_message(data, sub.msg_type),)
    else:
        with sub.handle:
            taken = sub.handle.take_message(sub.msg_type, sub.raw)
        if taken is None:
            return None
        args = tuple(taken) if with_info else (taken[0],)

    def deliver(msg_args):
        sub.callback(*msg_args)

    run = ENGINE.apply(rules, f"{subscriber}|{sub.topic_name}", subscriber, publisher, node, args, deliver)
    if run is None:
        return None

    async def _execute():
        await await_or_execute(run)

    return _execute


def _faulty_intra_hand_over(self, msg, targets) -> None:
    rules = ENGINE.rules_for(self.topic)
    if rules is not None and any(r.publishers for r in rules):
        _intra_sources[id(msg)] = (msg, self.node.get_fully_qualified_name())
        while len(_intra_sources) > INTRA_SOURCES:
            _intra_sources.popitem(last=False)
    _intra_hand_over(self, msg, targets)


def _faulty_intra_deliver(self, msg) -> None:
    rules = ENGINE.rules_for(self.topic)
    if rules is None or not self.intra:  # not intra: an rclpy subscription's, met at its take
        return _intra_deliver(self, msg)
    subscriber = self.node.get_fully_qualified_name()
    source = _intra_sources.get(id(msg))
    publisher = source[1] if source is not None and source[0] is msg else None

    def deliver(msg_args):
        _intra_deliver(self, msg_args[0])

    subscription = f"{subscriber}|{self.topic}"
    run = ENGINE.apply(rules, subscription, subscriber, publisher, self.node, (msg,), deliver, shared=True)
    if run is not None:
        run()


def install() -> None:
    """Put the engine in the two places (once per interpreter)."""
    if not ENGINE.installed:
        Executor._take_subscription = _faulty_take_subscription  # type: ignore[method-assign]
        intra_api.Subscription._deliver = _faulty_intra_deliver  # type: ignore[method-assign]
        intra_api.Publisher._hand_over = _faulty_intra_hand_over  # type: ignore[method-assign]
        ENGINE.installed = True


class MessageFaults(Node):
    """The engine's node: its ``faults`` parameter sets the rules, its
    ``~/counts`` service tells what each rule did."""

    def __init__(self, **kwargs):
        super().__init__(ENGINE_NODE_NAME, **kwargs)
        install()
        self.add_on_set_parameters_callback(self._on_set)
        self.declare_parameter("faults", "[]")
        self.create_service(Trigger, "~/counts", self._counts)

    def _on_set(self, params) -> SetParametersResult:
        for p in params:
            if p.name != "faults":
                continue
            try:
                rules = rules_from_text(p.value)
            except RuleError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            ENGINE.set_rules(rules)
        return SetParametersResult(successful=True)

    def _counts(self, request, response):
        response.success = True
        response.message = json.dumps(ENGINE.counts())
        return response


class MessageProbe(Node):
    """What a subscriber heard, seen from outside: every message it
    receives on ``topic`` (of ``type``, e.g. ``std_msgs/msg/UInt64``) it
    publishes again, unchanged, on ``~/heard``. Its subscription is an
    intra-process one where the load asks for it (container.intra)."""

    def __init__(self, **kwargs):
        super().__init__("message_probe", **kwargs)
        topic = self.declare_parameter("topic", "chatter").value
        msg_type = message_type(self.declare_parameter("type", "std_msgs/msg/String").value)
        self._pub = self.create_publisher(msg_type, "~/heard", 1000)
        self._sub = intra_api.create_subscription(self, msg_type, topic, self._heard, 1000)

    def _heard(self, msg) -> None:
        self._pub.publish(msg.to_message() if hasattr(msg, "to_message") else msg)


def message_type(name: str):
    """The message class ``package/msg/Type`` names; ValueError saying why not."""
    package, kind, type_name = (name.split("/") + ["", ""])[:3]
    try:
        if kind != "msg" or not type_name:
            raise ImportError("expected package/msg/Type")
        return getattr(importlib.import_module(f"{package}.msg"), type_name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"no message type {name!r}: {exc}") from None
