"""The ComponentEvent stream: what happened to which node, on a latched topic."""

from __future__ import annotations

import ctypes
import functools
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from cloneguard_interfaces.msg import ComponentEvent
from rclpy._rclpy_pybind11 import RCLError
from rclpy.exceptions import InvalidHandle
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

if TYPE_CHECKING:
    from rclpy._rclpy_pybind11 import Publisher as PublisherHandle
    from rclpy.node import Node

EVENTS_TOPIC = "~/_container/component_events"

# Late joiners (a launcher that subscribes after a load) still see the last
# 100 events, as with the upstream launcher this container is built for.
EVENTS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

LOADED = ComponentEvent.LOADED
UNLOADED = ComponentEvent.UNLOADED
LOAD_FAILED = ComponentEvent.LOAD_FAILED
CRASHED = ComponentEvent.CRASHED
REPAIRED = ComponentEvent.REPAIRED


def message(event_type: int, *, start_time_ns: int = 0, stamp_ns: int | None = None, **fields: Any) -> ComponentEvent:
    """One event, stamped now unless ``stamp_ns`` says when; ``fields``: any
    of ComponentEvent.msg's (unique_id, full_node_name, error_message, ...),
    the rest left at their defaults. The .msg is the one list of them."""
    unknown = sorted(set(fields) - set(ComponentEvent.get_fields_and_field_types()))
    if unknown:
        raise TypeError(f"ComponentEvent has no field {', '.join(unknown)}")
    msg = ComponentEvent(event_type=event_type, start_time=start_time_ns, **fields)
    now = time.time_ns() if stamp_ns is None else stamp_ns
    msg.stamp.sec, msg.stamp.nanosec = divmod(now, 1_000_000_000)
    return msg


class EventPublisher:
    def __init__(self, node: Node) -> None:
        self._node = node
        self._pub = node.create_publisher(ComponentEvent, EVENTS_TOPIC, EVENTS_QOS)

    def publish(self, event_type: int, **fields: Any) -> ComponentEvent | None:
        """Publish one event (``message``'s fields); the message, or None
        once the container's context is gone (nothing was published)."""
        msg = message(event_type, **fields)
        # Children can die while the container shuts down (they got the same
        # SIGTERM); once the context is gone there is no one to tell.
        if not self._context_ok():
            return None
        try:
            self._pub.publish(msg)
        except RCLError:
            if self._context_ok():
                raise
            return None
        return msg

    @property
    def handle(self) -> PublisherHandle:
        """rclpy's handle of the publisher underneath: whoever publishes on
        it from C (``publish_from_c``) keeps it in use (``with handle``)."""
        return self._pub.handle

    def publish_from_c(self) -> tuple[int, int, int]:
        """(the addresses of rclglue's cgr_event_publish and
        cgr_event_write_death, the rcl publisher's): what a thread without
        the GIL needs to publish events made by ``in_c`` here
        (isolated/clonecore/herald.c)."""
        from . import _rclglue

        ffi, lib = _rclglue.ffi, _rclglue.lib
        publish = ffi.cast("uintptr_t", ffi.addressof(lib, "cgr_event_publish"))
        write_death = ffi.cast("uintptr_t", ffi.addressof(lib, "cgr_event_write_death"))
        return int(publish), int(write_death), self.handle.pointer

    def _context_ok(self) -> bool:
        """Is the context still up? (Once destroyed, asking raises.)"""
        try:
            return self._node.context.ok()
        except InvalidHandle:
            return False


@dataclass(frozen=True)
class CEvent:
    """An event as rosidl's C message (``cloneguard_interfaces__msg__ComponentEvent``),
    for C that publishes it (isolated/clonecore/herald.c). Whoever holds it destroys
    it once: ``destroy()``, or the C it was handed to, with the function at
    ``destroy_address``."""

    pointer: int
    destroy_address: int

    def destroy(self) -> None:
        ctypes.CFUNCTYPE(None, ctypes.c_void_p)(self.destroy_address)(self.pointer)


def in_c(msg: ComponentEvent) -> CEvent:
    """``msg`` made into rosidl's C message by its type's own conversion
    (the functions rclpy's publish uses, from the capsules of the type
    support), so that the C side never restates the message's fields."""
    create, convert, destroy_address = _conversions()
    pointer = create()
    if not pointer:
        raise MemoryError("rosidl could not make a ComponentEvent")
    event = CEvent(pointer, destroy_address)
    if not convert(msg, pointer):
        event.destroy()
        raise ValueError(f"rosidl could not convert {msg!r}")
    return event


# CPython's PyCapsule_GetPointer, with a prototype of our own (setting
# argtypes on ctypes.pythonapi's would change it for every other user).
_capsule_pointer = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
    ("PyCapsule_GetPointer", ctypes.pythonapi)
)


@functools.cache
def _conversions() -> tuple[Any, Any, int]:
    """(create, convert, destroy's address) of ComponentEvent's type support,
    looked up once (each load arms a CRASHED event through them)."""
    cls = ComponentEvent
    if cls._CREATE_ROS_MESSAGE is None:
        cls.__class__.__import_type_support__()  # rosidl's metaclass

    def address(capsule: object) -> int:
        pointer = _capsule_pointer(capsule, None)
        assert pointer, "a type support capsule with no pointer"
        return int(pointer)

    create = ctypes.CFUNCTYPE(ctypes.c_void_p)(address(cls._CREATE_ROS_MESSAGE))
    convert = ctypes.PYFUNCTYPE(ctypes.c_bool, ctypes.py_object, ctypes.c_void_p)(address(cls._CONVERT_FROM_PY))
    return create, convert, address(cls._DESTROY_ROS_MESSAGE)
