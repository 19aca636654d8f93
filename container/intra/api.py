"""The component API: publishers and subscriptions that skip DDS inside a container.

    from cloneguard.container import intra

    self.pub = intra.create_publisher(self, String, "chatter", 10)
    self.sub = intra.create_subscription(self, String, "chatter", self.on_msg, 10)

Whether a node's endpoints are intra-process is decided by LoadNode's
``use_intra_process_comms`` extra argument (as upstream), or by the
``intra_process=`` keyword. When off they are plain rclpy endpoints.

When on, ``publish(msg)`` hands ``msg`` itself to every matching
intra-process subscription in the container (other nodes, other children,
same node) and wakes their executors; it also publishes over DDS when the
topic has subscribers that are not intra-process subscriptions of this
container. An intra-process subscription still receives from publishers
outside the container over DDS, and drops the DDS copy of messages from the
container's intra-process publishers (it got them by reference already).

QoS: history depth bounds each subscription's queue (KEEP_LAST drops the
oldest; KEEP_ALL is bounded at KEEP_ALL_LIMIT); a RELIABLE subscription does
not match a BEST_EFFORT publisher, as in DDS. Durability must be VOLATILE.

Large payloads: ``pub.loan(n)`` gives a buffer from the container's pool,
``pub.publish_loan(loan, msg, "data")`` sends ``msg`` with that buffer as its
``data`` field. Subscriptions made with ``loaned_field="data"`` get a
:class:`LoanedMessage` (read-only view, no copy); plain ones get a full
message (copied on their side). Rules: container/intra/README.md.
"""

from __future__ import annotations

import array
import functools
import threading
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .. import repairs
from .bus import PublisherEntry, SubscriptionEntry, get_bus, log
from .dds_reader import GidFilteredReader, publisher_gid
from .pool import Loan
from .queue import MessageQueue

if TYPE_CHECKING:
    from typing import Any, TypedDict, Unpack

    from rclpy.callback_groups import CallbackGroup
    from rclpy.node import Node
    from rclpy.subscription import Subscription as RclpySubscription

    class _PublisherOptions(TypedDict, total=False):
        """``create_publisher``'s keyword arguments: :class:`Publisher`'s."""

        intra_process: bool | None
        callback_group: CallbackGroup | None

    class _SubscriptionOptions(TypedDict, total=False):
        """``create_subscription``'s keyword arguments: :class:`Subscription`'s."""

        intra_process: bool | None
        loaned_field: str | None
        callback_group: CallbackGroup | None


KEEP_ALL_LIMIT = 10_000

# Which load a node belongs to and whether it asked for intra-process comms:
# set while its constructor runs (container.construction), remembered per node.
_constructing = threading.local()
_nodes: weakref.WeakKeyDictionary[object, tuple[object, bool]] = weakref.WeakKeyDictionary()
# The live intra-process endpoints of each node, for destroy_endpoints().
_endpoints: weakref.WeakKeyDictionary[object, list] = weakref.WeakKeyDictionary()


@contextmanager
def constructing(owner: object, enabled: bool) -> Iterator[None]:
    """The container builds a node inside this: endpoints the constructor
    makes belong to load ``owner`` and follow ``enabled``."""
    _constructing.load = (owner, enabled)
    try:
        yield
    finally:
        _constructing.load = None


def adopt(node: Node, owner: object, enabled: bool) -> None:
    """Remember ``node``'s load, for endpoints it creates after construction."""
    _nodes[node] = (owner, enabled)


def destroy_endpoints(node: Node) -> None:
    """Destroy every endpoint this API made for ``node``. Call it before
    ``node.destroy_node()``, which does not know about them (a subscription's
    DDS reader is a waitable of the node, not one of its subscriptions); the
    container does this for the nodes it unloads."""
    for endpoint in list(_endpoints.get(node, ())):
        endpoint.destroy()


def _track(node: Node, endpoint: Publisher | Subscription) -> None:
    _endpoints.setdefault(node, []).append(endpoint)


def _untrack(node: Node, endpoint: Publisher | Subscription) -> None:
    live = _endpoints.get(node)
    if live is not None and endpoint in live:
        live.remove(endpoint)


def _load_of(node: Node) -> tuple[object, bool]:
    known = _nodes.get(node)
    if known is not None:
        return known
    current = getattr(_constructing, "load", None)
    if current is not None:
        _nodes[node] = current
        return current
    return (None, False)


def _profile(qos: QoSProfile | int) -> QoSProfile:
    profile = QoSProfile(depth=qos) if isinstance(qos, int) else qos
    if profile.durability == DurabilityPolicy.TRANSIENT_LOCAL:
        raise ValueError(
            "intra-process endpoints support VOLATILE durability only "
            "(TRANSIENT_LOCAL history is not replayed in-process)"
        )
    return profile


# The field types a loan can stand for, and the array typecode rclpy uses for them.
_BYTE_FIELDS = {"sequence<uint8>": "B", "sequence<int8>": "b"}


def check_byte_field(msg_type: type[Any], field: str) -> str:
    kind = msg_type.get_fields_and_field_types().get(field)
    if kind is None:
        raise ValueError(f"{msg_type.__name__} has no field {field!r}")
    if kind not in _BYTE_FIELDS:
        raise ValueError(f"{msg_type.__name__}.{field} is {kind}: a loan can only be a uint8[] or int8[] field")
    return kind


class LoanedMessage:
    """A message whose big field lives in a loaned pool buffer.

    ``message`` holds every other field (the loaned one left empty),
    ``payload`` is a read-only view of the loaned bytes. Valid while this
    object is referenced; ``to_message()`` makes an ordinary (copied) one.
    """

    __slots__ = ("message", "field", "_loan", "_payload")

    def __init__(self, message: Any, field: str, loan: Loan | None = None, payload: memoryview | None = None) -> None:
        self.message = message
        self.field = field
        self._loan = loan
        self._payload = payload

    @property
    def payload(self) -> memoryview:
        if self._payload is None:
            assert self._loan is not None, "a loaned message has its payload or its loan"
            self._payload = self._loan.view()
        return self._payload

    @property
    def loaned(self) -> bool:
        """True if the payload is in the container's pool (not a DDS copy)."""
        return self._loan is not None

    def to_message(self) -> Any:
        """An ordinary message: the other fields shared, the payload copied."""
        full = type(self.message)()
        for name in self.message.get_fields_and_field_types():
            if name != self.field:
                setattr(full, name, getattr(self.message, name))
        data = array.array(_BYTE_FIELDS[check_byte_field(type(self.message), self.field)])
        data.frombytes(self.payload)
        setattr(full, self.field, data)
        return full

    @classmethod
    def wrap(cls, message: Any, field: str) -> LoanedMessage:
        """A DDS-received message seen through the same interface (no copy)."""
        return cls(message, field, None, memoryview(getattr(message, field)).toreadonly())


class Publisher:
    def __init__(
        self,
        node: Node,
        msg_type: type[Any],
        topic: str,
        qos: QoSProfile | int = 10,
        *,
        intra_process: bool | None = None,
        callback_group: CallbackGroup | None = None,
    ) -> None:
        owner, enabled = _load_of(node)
        self.intra = enabled if intra_process is None else intra_process
        profile = _profile(qos) if self.intra else (QoSProfile(depth=qos) if isinstance(qos, int) else qos)
        self.msg_type = msg_type
        self._dds = node.create_publisher(msg_type, topic, profile, callback_group=callback_group)
        self.node = node
        self.topic = self._dds.topic_name
        self.sent_intra = 0  # deliveries by reference (one per subscription)
        self.sent_dds = 0  # DDS publishes
        self._entry = None
        if self.intra:
            self._entry = PublisherEntry(
                owner,
                self.topic,
                msg_type,
                best_effort=profile.reliability == ReliabilityPolicy.BEST_EFFORT,
                gid=publisher_gid(self._dds),
            )
            get_bus().add_publisher(self._entry)
        _track(node, self)

    def publish(self, msg: Any) -> None:
        if not isinstance(msg, self.msg_type):
            raise TypeError(f"expected {self.msg_type.__name__}, got {type(msg).__name__}")
        if self._entry is None:
            self._dds.publish(msg)
            self.sent_dds += 1
            return
        targets = get_bus().targets(self._entry)
        self._hand_over(msg, targets)
        if self._outside_subscribers(targets):
            self._dds.publish(msg)
            self.sent_dds += 1

    def loan(self, nbytes: int) -> Loan:
        """A writable buffer of ``nbytes`` from the container's pool."""
        return get_bus().pool.loan(nbytes)

    def publish_loan(self, loan: Loan, message: Any, field: str) -> None:
        """Publish ``message`` with ``loan``'s bytes as its ``field``.

        ``message``'s own ``field`` should be empty; the loan is sealed (your
        writable view is released) and must not be reused."""
        if not isinstance(message, self.msg_type):
            raise TypeError(f"expected {self.msg_type.__name__}, got {type(message).__name__}")
        check_byte_field(self.msg_type, field)
        if loan.published:
            raise ValueError("this loan was already published")
        loan.seal()
        loaned = LoanedMessage(message, field, loan)
        targets = get_bus().targets(self._entry) if self._entry is not None else []
        self._hand_over(loaned, targets)
        if self._entry is None or self._outside_subscribers(targets):
            self._dds.publish(loaned.to_message())
            self.sent_dds += 1

    def get_subscription_count(self) -> int:
        """Subscriptions matched over DDS (intra-process ones included: they
        have a DDS reader too, for publishers outside the container)."""
        return self._dds.get_subscription_count()

    def destroy(self) -> None:
        if self._dds is None:
            return
        if self._entry is not None:
            get_bus().remove(self._entry)
            self._entry = None
        self.node.destroy_publisher(self._dds)
        self._dds = None  # type: ignore[assignment]  # destroyed: it publishes no more
        _untrack(self.node, self)

    def _hand_over(self, msg: object, targets: list[SubscriptionEntry]) -> None:
        for sub in targets:
            if sub.queue.put(msg):  # it was empty: its executor may be asleep
                try:
                    sub.wake()
                except Exception:  # destroyed meanwhile (unload): nothing to wake
                    pass
            self.sent_intra += 1

    def _outside_subscribers(self, targets: list[SubscriptionEntry]) -> bool:
        # Every intra-process target also has a DDS reader matched to us;
        # anything beyond them is a subscriber DDS has to serve.
        return self._dds.get_subscription_count() > len(targets)


class Subscription:
    def __init__(
        self,
        node: Node,
        msg_type: type[Any],
        topic: str,
        callback: Callable,
        qos: QoSProfile | int = 10,
        *,
        intra_process: bool | None = None,
        loaned_field: str | None = None,
        callback_group: CallbackGroup | None = None,
    ) -> None:
        owner, enabled = _load_of(node)
        self.intra = enabled if intra_process is None else intra_process
        if loaned_field is not None:
            check_byte_field(msg_type, loaned_field)
        self.node = node
        self.msg_type = msg_type
        self.callback = callback
        self.loaned_field = loaned_field
        self.received_intra = 0
        self.received_dds = 0
        self._entry = None
        if not self.intra:
            self._dds: RclpySubscription | None = node.create_subscription(
                msg_type, topic, self._on_dds, qos, callback_group=callback_group
            )
            self._reader = None
            self.topic = self._dds.topic_name
            _track(node, self)
            return
        profile = _profile(qos)
        self._dds = None
        self._reader = GidFilteredReader(
            node,
            msg_type,
            topic,
            profile,
            self._on_dds,
            drop_from=lambda gid: get_bus().is_intra_publisher(self.topic, gid),
            callback_group=callback_group,
        )
        self.topic = self._reader.topic_name
        capacity = KEEP_ALL_LIMIT if profile.history == HistoryPolicy.KEEP_ALL else max(1, profile.depth)
        self.queue = MessageQueue(capacity, on_repair=self._queue_repaired)
        self._wake = node.create_guard_condition(self._drain, callback_group=callback_group)
        # In a node process, publishers (maybe in other processes) wake it
        # through the waker the container opened for it; else directly.
        self._waker = get_bus().waker(owner) if owner is not None else None
        if self._waker is not None:
            self._token = self._waker.add(self._wake)
            wake: Callable[[], None] = functools.partial(self._waker.post, self._token)
        else:
            wake = self._wake.trigger
        self._entry = SubscriptionEntry(
            owner,
            self.topic,
            msg_type,
            reliable=profile.reliability == ReliabilityPolicy.RELIABLE,
            queue=self.queue,
            wake=wake,
        )
        get_bus().add_subscription(self._entry)
        _track(node, self)

    @property
    def dropped_dds_duplicates(self) -> int:
        return self._reader.dropped if self._reader is not None else 0

    def destroy(self) -> None:
        if self._entry is not None:
            get_bus().remove(self._entry)
            self._entry = None
            if self._waker is not None:
                self._waker.remove(self._token)
            self.node.destroy_guard_condition(self._wake)
            if self._reader is not None:
                self._reader.destroy()
        elif self._dds is not None:
            self.node.destroy_subscription(self._dds)
            self._dds = None
        _untrack(self.node, self)

    def _drain(self) -> None:
        for msg in self.queue.take_all():
            self.received_intra += 1
            self._deliver(msg)

    def _on_dds(self, msg: Any) -> None:
        self.received_dds += 1
        self._deliver(msg)

    def _deliver(self, msg: object) -> None:
        if self.loaned_field is not None:
            if isinstance(msg, LoanedMessage) and msg.field != self.loaned_field:
                msg = msg.to_message()
            if not isinstance(msg, LoanedMessage):
                msg = LoanedMessage.wrap(msg, self.loaned_field)
        elif isinstance(msg, LoanedMessage):
            msg = msg.to_message()
        self.callback(msg)

    def _queue_repaired(self, queue: MessageQueue) -> None:
        log.warning(
            f"intra-process queue of {self.topic} for {self.node.get_fully_qualified_name()}: "
            "the owner of its lock died holding it (EOWNERDEAD); repaired, "
            f"{len(queue)} message(s) kept"
        )
        if self._entry is not None and self._entry.owner is not None:
            repairs.record(
                repairs.INTRA_QUEUE,
                self._entry.owner,
                f"the intra-process queue of {self.topic}: {len(queue)} message(s) kept",
            )


def create_publisher(
    node: Node, msg_type: type[Any], topic: str, qos: QoSProfile | int = 10, **kwargs: Unpack[_PublisherOptions]
) -> Publisher:
    return Publisher(node, msg_type, topic, qos, **kwargs)


def create_subscription(
    node: Node,
    msg_type: type[Any],
    topic: str,
    callback: Callable,
    qos: QoSProfile | int = 10,
    **kwargs: Unpack[_SubscriptionOptions],
) -> Subscription:
    return Subscription(node, msg_type, topic, callback, qos, **kwargs)
