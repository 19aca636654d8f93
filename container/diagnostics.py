"""Each node's figures on ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``),
where ROS's monitors look (``ros2 topic echo /diagnostics``, rqt_robot_monitor,
diagnostic_aggregator): once a second, one status per loaded node, named
``<container>: <node>``, with its unique_id and pid and, where the allocator
guard counts them (isolated mode), its memory in use and its budget. A node
at ``NEAR_BUDGET`` of its budget or more is a WARN, "near its memory
budget"; else OK.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

if TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.timer import Timer

PERIOD_S = 1.0
TOPIC = "/diagnostics"
NEAR_BUDGET = 0.9
MiB = 1 << 20


Memory = tuple[int, int] | None  # (bytes in use, budget in bytes, 0: none); None: not counted


def status(container: str, full_name: str, unique_id: int, pid: int, memory: Memory) -> DiagnosticStatus:
    """One node's status; ``memory``: (bytes in use, budget in bytes, 0:
    none), or None where nothing counts it (thread mode)."""
    values = [KeyValue(key="unique_id", value=str(unique_id)), KeyValue(key="pid", value=str(pid))]
    level, message = DiagnosticStatus.OK, "running"
    if memory is not None:
        in_use, limit = memory
        values.append(KeyValue(key="memory_in_use_bytes", value=str(in_use)))
        values.append(KeyValue(key="memory_limit_bytes", value=str(limit)))
        message = f"{in_use / MiB:.1f} MiB in use" + (f" of its {limit / MiB:.1f} MiB budget" if limit else "")
        if limit and in_use >= NEAR_BUDGET * limit:
            level, message = DiagnosticStatus.WARN, f"near its memory budget: {message}"
    return DiagnosticStatus(
        level=level, name=f"{container}: {full_name}", message=message, hardware_id=container, values=values
    )


def publish_every_second(node: Node, nodes: Callable[[], Iterable[tuple[str, int, int, Memory]]]) -> Timer:
    """A timer on ``node`` that publishes the statuses of ``nodes()``:
    (full name, unique_id, pid, memory) each."""
    publisher = node.create_publisher(DiagnosticArray, TOPIC, 10)
    container = node.get_fully_qualified_name()

    def tick() -> None:
        array = DiagnosticArray(status=[status(container, *each) for each in nodes()])
        array.header.stamp = node.get_clock().now().to_msg()
        publisher.publish(array)

    return node.create_timer(PERIOD_S, tick)
