"""The demo robot's lifecycle node: the navigator serves its action only
while active, and the planner's death does not take that from it. The
test talks to the nodes as their own clients would (System.call,
send_goal, change_state, get_state: docs/testing-your-nodes.md); when it
ends, the harness stops the container and checks that nothing is left."""

import signal

from std_msgs.msg import UInt64
from std_srvs.srv import Trigger
from test_msgs.action import Fibonacci

from cloneguard.harness.system import NodeSpec

ROBOT = [
    NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 20.0}),
    NodeSpec("demo_robot", "demo_robot::Planner"),
    NodeSpec("demo_robot", "demo_robot::MapServer"),
    NodeSpec("demo_robot", "demo_robot::Navigator"),
]
SUCCEEDED = 4  # action_msgs/GoalStatus
ROUTE = [0, 1, 1, 2, 3, 5]  # the result of a goal of order 5


def test_the_navigator_serves_goals_only_while_active_and_outlives_the_planner(system_factory):
    robot = system_factory(ROBOT)
    reached = robot.topic(UInt64, "/goals_reached")  # its lifecycle publisher
    assert robot.get_state("/navigator") == "unconfigured"
    assert not robot.send_goal(Fibonacci, "/navigator/navigate", Fibonacci.Goal(order=5)).accepted

    assert robot.change_state("/navigator", "configure")
    assert robot.change_state("/navigator", "activate")
    assert robot.get_state("/navigator") == "active"
    outcome = robot.send_goal(Fibonacci, "/navigator/navigate", Fibonacci.Goal(order=5))
    assert outcome.accepted and outcome.status == SUCCEEDED
    assert list(outcome.result.sequence) == ROUTE

    # another node dies: the navigator, in a process of its own, stays active and serves on
    navigator = robot.node("/navigator")
    robot.kill("/planner", signal.SIGKILL)
    assert robot.wait_crashed("/planner").exit_signal == signal.SIGKILL
    assert robot.get_state("/navigator") == "active"
    outcome = robot.send_goal(Fibonacci, "/navigator/navigate", Fibonacci.Goal(order=5))
    assert outcome.accepted and outcome.status == SUCCEEDED
    assert list(outcome.result.sequence) == ROUTE
    assert robot.node("/navigator").pid == navigator.pid
    reached.wait_for(lambda m: m.data == 2, timeout=10)  # published while active
    answer = robot.call(Trigger, "/map_server/get_map", Trigger.Request())
    assert answer.success and answer.message == "warehouse"

    # inactive: the action server is there, and rejects goals
    assert robot.change_state("/navigator", "deactivate")
    assert robot.get_state("/navigator") == "inactive"
    assert not robot.send_goal(Fibonacci, "/navigator/navigate", Fibonacci.Goal(order=5)).accepted
    assert robot.change_state("/navigator", "cleanup")
    assert robot.get_state("/navigator") == "unconfigured"
    assert not robot.change_state("/navigator", "deactivate")  # no such transition from there
