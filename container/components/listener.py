"""Demo component: counts what arrives on a topic and publishes the count.

The count goes out on ``~/received`` each time a message arrives, so an
observer outside the container can tell that this node is still receiving.
Its subscription is an intra-process one (container.intra): loaded with
``use_intra_process_comms`` it gets the container's messages by reference and
the rest over DDS, each message once; ``~/by_reference`` counts the
messages that came by reference.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rclpy.node import Node
from std_msgs.msg import String, UInt64

from cloneguard.container import intra

if TYPE_CHECKING:
    from typing import Any


class Listener(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("listener", **kwargs)
        topic = self.declare_parameter("topic", "chatter").value
        self.received = 0
        self._count_pub = self.create_publisher(UInt64, "~/received", 10)
        self._by_ref_pub = self.create_publisher(UInt64, "~/by_reference", 10)
        self._sub = intra.create_subscription(self, String, topic, self._on_message, 10)

    def _on_message(self, msg: String) -> None:
        self.received += 1
        self._count_pub.publish(UInt64(data=self.received))
        self._by_ref_pub.publish(UInt64(data=self._sub.received_intra))
