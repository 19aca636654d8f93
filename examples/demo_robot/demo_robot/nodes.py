"""The demo robot's nodes: plain rclpy nodes, nothing cloneguard-specific
(a component is a Node subclass, a LifecycleNode too, whose constructor
takes ``**kwargs``)."""

from __future__ import annotations

from rclpy.action import ActionServer, GoalResponse
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.node import Node
from std_msgs.msg import Float64, UInt64
from std_srvs.srv import Trigger
from test_msgs.action import Fibonacci


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


class Navigator(LifecycleNode):
    """A lifecycle node serving ``~/navigate`` (test_msgs/Fibonacci, standing
    in for a navigation action: a route of ``order`` legs, one feedback per
    leg). It accepts goals only while active and rejects them otherwise;
    while active it publishes how many goals it reached on ``/goals_reached``
    (a lifecycle publisher, made on configure)."""

    def __init__(self, **kwargs):
        super().__init__("navigator", **kwargs)
        self._active = False
        self._reached = 0
        self._pub = None
        self._server = ActionServer(self, Fibonacci, "~/navigate", self._navigate, goal_callback=self._goal)

    def on_configure(self, state):
        self._pub = self.create_lifecycle_publisher(UInt64, "/goals_reached", 10)
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state):
        self._active = True
        return super().on_activate(state)  # activates the lifecycle publisher

    def on_deactivate(self, state):
        self._active = False
        return super().on_deactivate(state)

    def on_cleanup(self, state):
        self.destroy_lifecycle_publisher(self._pub)
        self._pub = None
        return TransitionCallbackReturn.SUCCESS

    def _goal(self, _goal):
        return GoalResponse.ACCEPT if self._active else GoalResponse.REJECT

    def _navigate(self, goal_handle):
        route = [0, 1]
        for _ in range(goal_handle.request.order - 1):
            route.append(route[-1] + route[-2])
            goal_handle.publish_feedback(Fibonacci.Feedback(sequence=route))
        goal_handle.succeed()
        self._reached += 1
        self._pub.publish(UInt64(data=self._reached))
        return Fibonacci.Result(sequence=route)
