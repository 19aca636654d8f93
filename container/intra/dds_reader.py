"""The DDS side of an intra-process subscription: a reader that knows who sent what.

An intra-process subscription gets the messages of the container's
intra-process publishers by reference, and everything else over DDS. Such a
publisher also publishes over DDS when there are subscribers outside the
container, so the subscription would see those messages twice. rclpy's take
gives no publisher gid, so :class:`GidFilteredReader` takes from the rcl
subscription itself (container/rclglue/rclglue.c: rcl_take_serialized_message
with its rmw_message_info_t) and drops each message whose publisher gid
``drop_from`` claims, before deserializing it.

It is an rclpy :class:`~rclpy.waitable.Waitable` on the node, not an rclpy
Subscription: the subscription handle is never in ``node.subscriptions``, so
the executor only waits on it (through us) and never takes from it itself.

    reader = GidFilteredReader(node, String, "chatter", 10, on_msg,
                               drop_from=lambda gid: gid in intra_gids)
    ...
    reader.destroy()

:func:`publisher_gid` gives an rclpy publisher's gid, the same 16 bytes the
reader sees on the messages that publisher sent.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rclpy.callback_groups import CallbackGroup
from rclpy.exceptions import InvalidHandle
from rclpy.executors import await_or_execute
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message
from rclpy.type_support import check_is_valid_msg_type
from rclpy.waitable import NumberOfEntities, Waitable

from .._rclglue import ffi, lib

if TYPE_CHECKING:
    from types import TracebackType

    from rclpy._rclpy_pybind11 import Publisher as PublisherHandle
    from rclpy._rclpy_pybind11 import Subscription as SubscriptionHandle
    from rclpy._rclpy_pybind11 import WaitSet
    from rclpy.node import Node
    from rclpy.publisher import Publisher

GID_SIZE = lib.CGR_GID_SIZE

# Capacity the take buffer starts with. The rmw grows it when a message does
# not fit and it is never shrunk: a reader keeps its largest message's size
# allocated until destroy().
INITIAL_CAPACITY = 4096
# Upper bound on messages taken in one take_data(): a publisher faster than
# our callbacks must not keep one take_data() going forever.  What is left
# stays in the DDS reader, which keeps the wait set ready for the next round.
MAX_BATCH = 10_000


def _error_text(buf: Any) -> str:
    return ffi.string(buf).decode("utf-8", "replace")


def publisher_gid(publisher: Publisher | PublisherHandle) -> bytes:
    """The DDS gid (16 bytes) of an rclpy Publisher (or its ``handle``).

    It is what a :class:`GidFilteredReader` passes to ``drop_from`` for the
    messages this publisher sent. Fixed for the publisher's lifetime.
    """
    handle: PublisherHandle = getattr(publisher, "handle", publisher)
    gid = ffi.new("uint8_t[]", GID_SIZE)
    err = ffi.new("char[]", lib.CGR_ERR_SIZE)
    with handle:  # in use: rclpy will not finalize it during the call
        rc = lib.cgr_publisher_gid(ffi.cast("rcl_publisher_t *", handle.pointer), gid, err, len(err))
    if rc != 0:
        raise RuntimeError(f"cannot get the publisher's gid: {_error_text(err)}")
    return ffi.buffer(gid)[:]


class TakeBuffer:
    """A reusable rcl_serialized_message_t and the gid/error buffers for takes.

    Not thread-safe: the reader uses it under its lock.
    """

    def __init__(self, capacity: int = INITIAL_CAPACITY):
        self.gid = ffi.new("uint8_t[]", GID_SIZE)
        self.err = ffi.new("char[]", lib.CGR_ERR_SIZE)
        msg = ffi.new("rcl_serialized_message_t *")  # zeroed
        if lib.cgr_message_init(msg, capacity, self.err, len(self.err)) != 0:
            raise MemoryError(f"cannot allocate a take buffer: {_error_text(self.err)}")
        # ffi.gc frees the rcutils buffer if release() is never called;
        # ffi.release() runs the same destructor now (and only once).
        self.msg = ffi.gc(msg, lib.cgr_message_fini)

    def take(self, subscription_pointer: int) -> tuple[bytes, bytes] | None:
        """(serialized message, publisher gid), None when there is nothing to take."""
        rc = lib.cgr_take_serialized(
            ffi.cast("rcl_subscription_t *", subscription_pointer), self.msg, self.gid, self.err, len(self.err)
        )
        if rc == lib.CGR_NOT_TAKEN:
            return None
        if rc != lib.CGR_TAKEN:
            raise RuntimeError(_error_text(self.err))
        # One copy out of the rcutils buffer: rclpy's deserializer wants bytes.
        data = ffi.buffer(self.msg.buffer, self.msg.buffer_length)[:]
        return data, ffi.buffer(self.gid)[:]

    def release(self) -> None:
        if self.msg is not None:
            ffi.release(self.msg)
            self.msg = None


class GidFilteredReader(Waitable):
    """A DDS subscription that drops messages by publisher gid.

    ``callback(msg)`` is called (by the node's executor, in ``callback_group``,
    default the node's) for every message on ``topic`` whose publisher gid
    ``drop_from(gid)`` (16 bytes) does not claim; ``dropped`` counts the others.
    ``qos_profile`` is a QoSProfile or a history depth, as for
    ``node.create_subscription`` (QoS overriding parameters are not declared).

    Call :meth:`destroy` when done (destroying the node does not).
    """

    def __init__(
        self,
        node: Node,
        msg_type: type[Any],
        topic: str,
        qos_profile: QoSProfile | int,
        callback: Callable[[Any], Any],
        drop_from: Callable[[bytes], bool],
        callback_group: CallbackGroup | None = None,
    ) -> None:
        if isinstance(qos_profile, int):
            if qos_profile < 0:
                raise ValueError("history depth must be greater than or equal to zero")
            qos_profile = QoSProfile(depth=qos_profile)
        elif not isinstance(qos_profile, QoSProfile):
            raise TypeError(f"Expected QoSProfile or int, but received {qos_profile!r}")
        check_is_valid_msg_type(msg_type)  # also loads its type support

        # The same construction as node.create_subscription(), minus the rclpy
        # Subscription object that would put the handle in node.subscriptions.
        try:
            with node.handle:
                self._handle = _rclpy.Subscription(node.handle, msg_type, topic, qos_profile.get_c_qos_profile())
        except ValueError:
            # As create_subscription(): a bad topic name is an
            # InvalidTopicNameException naming the problem.
            node._validate_topic_or_service_name(topic)
            raise
        try:
            with self._handle:
                self.topic_name: str = self._handle.get_topic_name()
            self._buffer = TakeBuffer()
        except BaseException:
            self._handle.destroy_when_not_in_use()
            raise

        super().__init__(callback_group or node.default_callback_group)
        self.node = node
        self.msg_type = msg_type
        self.qos_profile = qos_profile
        self.callback = callback
        self.drop_from = drop_from
        self.received = 0  # messages handed to callback (taken and not dropped)
        self.dropped = 0  # messages drop_from claimed
        self.taken_bytes = 0  # CDR bytes of every message taken, dropped ones included
        # Guards the take buffer against destroy() from another thread.
        self._lock = threading.Lock()
        self._index: int | None = None  # our slot in the current wait set
        self._destroyed = False
        node.add_waitable(self)

    @property
    def handle(self) -> SubscriptionHandle:
        """The rclpy (pybind) Subscription handle; ``handle.pointer`` is the rcl_subscription_t *."""
        return self._handle

    def get_publisher_count(self) -> int:
        with self._handle:
            return self._handle.get_publisher_count()

    # --- Waitable API (rclpy 7.1, rclpy/waitable.py) -------------------------

    def __enter__(self) -> None:
        # The executor enters every waitable before building the wait set:
        # the handle stays in use (not finalizable) until __exit__. Raises
        # InvalidHandle once destroyed; the executor then leaves us out of
        # the entity count.
        self._handle.__enter__()

    def __exit__(self, t: type[BaseException] | None, v: BaseException | None, tb: TracebackType | None) -> None:
        self._handle.__exit__(t, v, tb)

    def get_num_entities(self) -> NumberOfEntities:
        return NumberOfEntities(num_subs=1)

    def add_to_wait_set(self, wait_set: WaitSet) -> None:
        # rclpy 7.1's executor calls this even for a waitable whose __enter__
        # raised InvalidHandle (it only skips counting it): then there is no
        # slot for us in the wait set, so add nothing.
        self._index = None
        try:
            with self._handle:
                self._index = wait_set.add_subscription(self._handle)
        except InvalidHandle:
            pass

    def is_ready(self, wait_set: WaitSet) -> bool:
        return self._index is not None and wait_set.is_ready("subscription", self._index)

    def take_data(self) -> tuple[list[Any], Exception | None]:
        """Take every message there is (up to MAX_BATCH), deserialize those not dropped.

        Returns (messages, error): an error met after some messages were taken
        is raised by execute() once those have been delivered.
        """
        messages: list = []
        with self._lock:
            if self._destroyed:
                return messages, None
            try:
                with self._handle:
                    pointer = self._handle.pointer
                    for _ in range(MAX_BATCH):
                        taken = self._buffer.take(pointer)
                        if taken is None:
                            break
                        data, gid = taken
                        self.taken_bytes += len(data)
                        if self.drop_from(gid):
                            self.dropped += 1
                            continue
                        messages.append(deserialize_message(data, self.msg_type))
            except InvalidHandle:
                pass  # destroyed meanwhile: nothing more to take
            except Exception as exc:  # noqa: BLE001 - re-raised by execute()
                return messages, exc
        return messages, None

    async def execute(self, taken_data: tuple[list[Any], Exception | None]) -> None:
        if not taken_data:
            return
        messages, error = taken_data
        for msg in messages:
            self.received += 1
            await await_or_execute(self.callback, msg)
        if error is not None:
            raise RuntimeError(f"taking from {self.topic_name} failed: {error}") from error

    # --- end of the Waitable API ----------------------------------------------

    def destroy(self) -> None:
        """Leave the node's executor and destroy the subscription. Idempotent.

        The rcl subscription is finalized as soon as no wait set or take is
        using it (it may be, in another executor thread, right now).
        """
        with self._lock:
            if self._destroyed:
                return
            self._destroyed = True
            self._buffer.release()
        try:
            self.node.remove_waitable(self)
        except ValueError:
            pass  # not (or no longer) on the node
        self._handle.destroy_when_not_in_use()
