"""The demo robot's claims: when the planner dies, odometry keeps flowing
and the map server still answers (once, and as seeded trials with a rate
in the report); with a restart policy the planner is back. Run with
``python -m pytest examples/demo_robot/scenarios`` once the package is
installed (docs/testing-your-nodes.md)."""

import signal
import time
from pathlib import Path

import pytest
from demo_robot.faults import PLANNER_HOLDING_A_LOCK
from std_msgs.msg import Float64, UInt64
from std_srvs.srv import Trigger

from cloneguard.harness.composition import read_composition
from cloneguard.harness.schedule import At, Freeze, Kill, Starve, random_over
from cloneguard.harness.system import NodeSpec, call_latency, longest_gap, rate

ROBOT = [
    NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 20.0}),
    NodeSpec("demo_robot", "demo_robot::Planner"),
    NodeSpec("demo_robot", "demo_robot::MapServer"),
]
#: The same composition, as the robot's launch file starts it.
LAUNCH = Path(__file__).resolve().parent.parent / "launch" / "robot.launch.xml"
WINDOW = 40  # odometry messages after the fault the claims are judged on (2 s)


@pytest.mark.parametrize("sig", [signal.SIGSEGV, signal.SIGKILL], ids=["SIGSEGV", "SIGKILL"])
def test_odometry_and_the_map_outlive_the_planner(system_factory, sig):
    robot = system_factory(read_composition(LAUNCH))  # its nodes, and its container's --isolated
    odom = robot.topic(Float64, "/odom")
    odom.wait_count(5, timeout=10)

    died_at = robot.kill("/planner", sig)
    crashed = robot.wait_crashed("/planner")
    odom.wait_count(len(odom) + WINDOW, timeout=10)

    assert crashed.exit_signal == sig
    assert rate(odom, died_at) >= 9.0
    assert longest_gap(odom, died_at) < 0.5
    assert call_latency(robot, robot.service(Trigger, "/map_server/get_map"), Trigger.Request()) < 0.5
    assert robot.alive()


def test_the_rest_outlives_the_planner_killed_at_a_random_instant(system_factory, system_trials):
    robot = system_factory(ROBOT)
    odom = robot.topic(Float64, "/odom")
    robot.topic(UInt64, "/plan")  # watched too: the report shows it stop and come back
    odom.wait_count(5, timeout=10)
    get_map = robot.service(Trigger, "/map_server/get_map")

    def trial(t):
        t.pause(0.5)  # a random instant of the planner's work
        died_at = robot.kill("/planner", signal.SIGKILL)
        robot.wait_crashed("/planner")
        odom.wait_count(len(odom) + WINDOW // 2, timeout=10)
        assert rate(odom, died_at) >= 9.0
        assert longest_gap(odom, died_at) < 0.5
        return {"get_map": 1e3 * call_latency(robot, get_map, Trigger.Request())}

    system_trials(
        robot,
        trial,
        fault="planner SIGKILL at a random instant",
        claim="odometry keeps >= 9 Hz with no gap of 0.5 s and the map server answers",
        quick=3,
        at_least=0.99,
    )


def test_the_map_server_answers_through_a_random_schedule_of_faults(system_factory, system_trials):
    robot = system_factory(ROBOT)
    odom = robot.topic(Float64, "/odom")
    odom.wait_count(5, timeout=10)
    get_map = robot.service(Trigger, "/map_server/get_map")

    def trial(t):
        # odometry frozen or starved twice at random over a second, and the
        # planner segfaulting at a random instant of it
        odometry = [Freeze("/odometry", 0.3), Starve("/odometry", 0.01, 0.5)]
        schedule = random_over(t.rng, 1.0, odometry, count=2) + [
            At(t.rng.uniform(0, 1), Kill("/planner", signal.SIGSEGV))
        ]
        robot.inject(schedule)
        robot.wait_crashed("/planner")
        latency = call_latency(robot, get_map, Trigger.Request())
        over = time.monotonic_ns()
        odom.wait_count(len(odom) + WINDOW // 2, timeout=10)
        assert latency < 0.5
        assert rate(odom, over) >= 9.0  # odometry back to speed once the faults are over
        return {"get_map": 1e3 * latency}

    system_trials(
        robot,
        trial,
        fault="odometry frozen and starved, planner SIGSEGV (random schedule)",
        claim="the map server answers within 0.5 s and odometry is back at >= 9 Hz",
        quick=3,
        at_least=0.99,
    )


def test_the_planner_is_back_under_a_restart_policy(system_factory):
    robot = system_factory(ROBOT, ["--isolated", "--restart-policy", "on-crash"])
    plans = robot.topic(UInt64, "/plan")
    plans.wait_count(5, timeout=10)

    before = robot.node("/planner")
    robot.kill("/planner", signal.SIGSEGV)
    back = robot.wait_back("/planner", timeout=10)
    plans.wait_count(len(plans) + 5, timeout=10)  # it plans again

    assert back.pid != before.pid and back.unique_id != before.unique_id


def test_the_rest_outlives_the_planner_killed_holding_a_lock(system_factory, system_trials):
    PLANNER_HOLDING_A_LOCK.run(system_factory, system_trials)  # demo_robot/faults.py
