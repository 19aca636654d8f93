"""Demo component: publishes ``<message> <n>`` on a topic from a timer.

Its publisher is an intra-process one (container.intra): loaded with
``use_intra_process_comms`` it hands each message to the container's other
nodes by reference, and to DDS only for subscribers outside the container.
``limit`` > 0 stops it after that many messages.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rclpy.node import Node
from std_msgs.msg import String

from cloneguard.container import intra

from . import checks

if TYPE_CHECKING:
    from typing import Any


class Talker(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("talker", **kwargs)
        topic = self.declare_parameter("topic", "chatter").value
        period = checks.period(self.declare_parameter("period", 0.1).value)
        self._text = self.declare_parameter("message", "hello").value
        self._limit = checks.count(self.declare_parameter("limit", 0).value, "limit")
        self._count = 0
        self._pub = intra.create_publisher(self, String, topic, 10)
        self._timer = self.create_timer(period, self._tick)

    def _tick(self) -> None:
        if self._limit and self._count >= self._limit:
            self._timer.cancel()
            return
        self._count += 1
        self._pub.publish(String(data=f"{self._text} {self._count}"))
