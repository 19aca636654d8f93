"""The demo robot's nodes: plain rclpy nodes, nothing cloneguard-specific
(a component is a Node subclass whose constructor takes ``**kwargs``)."""

from __future__ import annotations

from rclpy.node import Node
from std_msgs.msg import Float64, UInt64
from std_srvs.srv import Trigger


class Odometry(Node):
    """Publishes the distance driven on ``/odom`` at ``rate`` Hz."""

    def __init__(self, **kwargs):
        super().__init__("odometry", **kwargs)
        self._distance = 0.0
        self._pub = self.create_publisher(Float64, "/odom", 10)
        self._timer = self.create_timer(1.0 / self.declare_parameter("rate", 20.0).value, self._tick)

    def _tick(self):
        self._distance += 0.05
        self._pub.publish(Float64(data=self._distance))


class Planner(Node):
    """Plans on every odometry message; publishes how many plans on ``/plan``."""

    def __init__(self, **kwargs):
        super().__init__("planner", **kwargs)
        self._plans = 0
        self._pub = self.create_publisher(UInt64, "/plan", 10)
        self._sub = self.create_subscription(Float64, "/odom", self._plan, 10)

    def _plan(self, _odom):
        self._plans += 1
        self._pub.publish(UInt64(data=self._plans))


class MapServer(Node):
    """Answers ``~/get_map`` (std_srvs/Trigger) with the map's name."""

    def __init__(self, **kwargs):
        super().__init__("map_server", **kwargs)
        self._map = self.declare_parameter("map", "warehouse").value
        self._srv = self.create_service(Trigger, "~/get_map", self._get_map)

    def _get_map(self, _request, response):
        response.success = True
        response.message = self._map
        return response
