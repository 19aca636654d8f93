"""Demo component: a counter on ``~/heartbeat`` at a fixed rate.

A gap in the sequence, or its end, is how the harness sees that a node (or
the process spinning it) stopped making progress. Its publisher takes
rclpy's QoS overrides (``qos_overrides.<topic>.publisher.history``,
``.depth``, ``.reliability``), as a publisher made with
``QoSOverridingOptions`` does.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rclpy.node import Node
from rclpy.qos_overriding_options import QoSOverridingOptions
from std_msgs.msg import UInt64

from . import checks

if TYPE_CHECKING:
    from typing import Any


class Heartbeat(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("heartbeat", **kwargs)
        period = checks.period(self.declare_parameter("period", 0.05).value)
        self._beats = 0
        self._pub = self.create_publisher(
            UInt64, "~/heartbeat", 10, qos_overriding_options=QoSOverridingOptions.with_default_policies()
        )
        self._timer = self.create_timer(period, self._beat)

    def _beat(self) -> None:
        self._beats += 1
        self._pub.publish(UInt64(data=self._beats))
