"""Demo component: a counter on ``~/heartbeat`` at a fixed rate.

A gap in the sequence, or its end, is how the harness sees that a node (or
the process spinning it) stopped making progress.
"""
from rclpy.node import Node
from std_msgs.msg import UInt64

from . import checks


class Heartbeat(Node):
    def __init__(self, **kwargs):
        super().__init__("heartbeat", **kwargs)
        period = checks.period(self.declare_parameter("period", 0.05).value)
        self._beats = 0
        self._pub = self.create_publisher(UInt64, "~/heartbeat", 10)
        self._timer = self.create_timer(period, self._beat)

    def _beat(self):
        self._beats += 1
        self._pub.publish(UInt64(data=self._beats))
