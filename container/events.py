"""The ComponentEvent stream: what happened to which node, on a latched topic."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

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


class EventPublisher:
    def __init__(self, node: Node) -> None:
        self._node = node
        self._pub = node.create_publisher(ComponentEvent, EVENTS_TOPIC, EVENTS_QOS)

    def publish(
        self,
        event_type: int,
        *,
        unique_id: int = 0,
        full_node_name: str = "",
        package_name: str = "",
        plugin_name: str = "",
        error_message: str = "",
        pid: int = 0,
        exit_signal: int = 0,
        exit_code: int = 0,
        start_time_ns: int = 0,
        allocator_quarantined: bool = False,
        repaired_state: str = "",
        stamp_ns: int | None = None,
    ) -> ComponentEvent:
        now = time.time_ns() if stamp_ns is None else stamp_ns
        msg = ComponentEvent()
        msg.stamp.sec, msg.stamp.nanosec = divmod(now, 1_000_000_000)
        msg.event_type = event_type
        msg.unique_id = unique_id
        msg.full_node_name = full_node_name
        msg.package_name = package_name
        msg.plugin_name = plugin_name
        msg.error_message = error_message
        msg.pid = pid
        msg.exit_signal = exit_signal
        msg.exit_code = exit_code
        msg.start_time = start_time_ns
        msg.allocator_quarantined = allocator_quarantined
        msg.repaired_state = repaired_state
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

    def publish_from_c(self) -> tuple[int, int]:
        """(the address of rclglue's cgr_publish_cdr, the rcl publisher's):
        what a thread without the GIL needs to publish serialized events
        here (isolated/herald.c)."""
        from . import _rclglue

        publish = _rclglue.ffi.cast("uintptr_t", _rclglue.ffi.addressof(_rclglue.lib, "cgr_publish_cdr"))
        return int(publish), self.handle.pointer

    def _context_ok(self) -> bool:
        """Is the context still up? (Once destroyed, asking raises.)"""
        try:
            return self._node.context.ok()
        except InvalidHandle:
            return False
