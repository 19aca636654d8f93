"""Demo component: counts what arrives on a topic and publishes the count.

The count goes out on ``~/received`` each time a message arrives, so an
observer outside the container can tell that this node is still receiving.
"""
from rclpy.node import Node
from std_msgs.msg import String, UInt64


class Listener(Node):
    def __init__(self, **kwargs):
        super().__init__("listener", **kwargs)
        topic = self.declare_parameter("topic", "chatter").value
        self.received = 0
        self._count_pub = self.create_publisher(UInt64, "~/received", 10)
        self._sub = self.create_subscription(String, topic, self._on_message, 10)

    def _on_message(self, msg):
        self.received += 1
        self._count_pub.publish(UInt64(data=self.received))
