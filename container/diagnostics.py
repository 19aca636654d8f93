"""Each node's figures on ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``),
where ROS's monitors look (``ros2 topic echo /diagnostics``, rqt_robot_monitor,
diagnostic_aggregator): once a second (the container node's parameter
``diagnostic_updater.period``, as ROS's diagnostic_updater names it, says
otherwise: ``--ros-args -p diagnostic_updater.period:=0.1``), one status per loaded node, named
``<container>: <node>``, with its unique_id and pid and, where the allocator
guard counts them (isolated mode), its memory in use and its budget. A node
at ``NEAR_BUDGET`` of its budget or more is a WARN, "near its memory
budget"; else OK.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor

if TYPE_CHECKING:
    from rclpy.node import Node
    from rclpy.timer import Timer

PERIOD_S = 1.0
PERIOD_PARAMETER = "diagnostic_updater.period"
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


def declared_period(node: Node) -> float:
    """``node``'s ``diagnostic_updater.period``, declared: the seconds
    between two publications (PERIOD_S unless the command line sets it;
    read once, at start). ValueError, saying what it takes, if it is not a
    number of seconds above 0."""
    descriptor = ParameterDescriptor(
        description="seconds between two publications of the nodes' statuses on /diagnostics",
        dynamic_typing=True,  # 1 and 1.0 alike
        read_only=True,
    )
    value = node.declare_parameter(PERIOD_PARAMETER, PERIOD_S, descriptor).value
    if isinstance(value, bool) or not isinstance(value, int | float) or not (value > 0 and math.isfinite(value)):
        raise ValueError(f"{PERIOD_PARAMETER} is the seconds between two /diagnostics publications, not {value!r}")
    return float(value)


def publish_every(node: Node, period_s: float, nodes: Callable[[], Iterable[tuple[str, int, int, Memory]]]) -> Timer:
    """A timer on ``node`` that publishes the statuses of ``nodes()``:
    (full name, unique_id, pid, memory) each, every ``period_s``."""
    publisher = node.create_publisher(DiagnosticArray, TOPIC, 10)
    container = node.get_fully_qualified_name()

    def tick() -> None:
        array = DiagnosticArray(status=[status(container, *each) for each in nodes()])
        array.header.stamp = node.get_clock().now().to_msg()
        publisher.publish(array)

    return node.create_timer(period_s, tick)
