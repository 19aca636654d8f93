"""The demo robot's faults by name (entry point group
``cloneguard.harness.faults`` in pyproject.toml): its scenarios run them,
and ``python -m cloneguard.harness reproduce planner-holding-a-lock``
replays them. Only the harness imports this module; the nodes never do."""

from std_msgs.msg import Float64

from cloneguard.harness.named_faults import NamedFault
from cloneguard.harness.system import NodeSpec, longest_gap, rate

ROBOT = [
    NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 20.0}),
    NodeSpec("demo_robot", "demo_robot::Planner"),
    NodeSpec("demo_robot", "demo_robot::MapServer"),
]


def planner_holding_a_lock(robot):
    """Watch odometry; each trial kills the planner just after it took a
    Python lock (with the GIL), then judges the next second of odometry."""
    odom = robot.topic(Float64, "/odom")
    odom.wait_count(5, timeout=10)

    def trial(t):
        t.pause(0.3)
        died_at = robot.kill_at("/planner", "python-lock")
        robot.wait_crashed("/planner")
        odom.wait_count(len(odom) + 20, timeout=10)
        assert rate(odom, died_at) >= 9.0
        assert longest_gap(odom, died_at) < 0.5

    return trial


PLANNER_HOLDING_A_LOCK = NamedFault(
    fault="planner SIGKILL holding a Python lock",
    claim="odometry keeps >= 9 Hz with no gap of 0.5 s",
    nodes=ROBOT,
    trials=planner_holding_a_lock,
    at_least=0.99,
)
