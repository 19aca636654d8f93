"""Demo component: publishes ``<message> <n>`` on a topic from a timer."""
from rclpy.node import Node
from std_msgs.msg import String


class Talker(Node):
    def __init__(self, **kwargs):
        super().__init__("talker", **kwargs)
        topic = self.declare_parameter("topic", "chatter").value
        period = self.declare_parameter("period", 0.1).value
        self._text = self.declare_parameter("message", "hello").value
        if period <= 0:
            raise ValueError(f"parameter 'period' must be positive, got {period}")
        self._count = 0
        self._pub = self.create_publisher(String, topic, 10)
        self._timer = self.create_timer(period, self._tick)

    def _tick(self):
        self._count += 1
        self._pub.publish(String(data=f"{self._text} {self._count}"))
