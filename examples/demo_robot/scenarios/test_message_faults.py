"""The demo robot under faults on its messages, its nodes unchanged: the
planner loses half its odometry, then gets it 300 ms late. Each a seeded
trial: the seed replays which odometry messages were lost."""

from std_msgs.msg import Float64, UInt64

from cloneguard.harness.schedule import Delay, Drop
from cloneguard.harness.system import NodeSpec, longest_gap, rate
from cloneguard.harness.system_trials import Measure

ROBOT = [
    NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 20.0}),
    NodeSpec("demo_robot", "demo_robot::Planner"),
]


def test_the_planner_plans_on_what_odometry_still_arrives(system_factory, system_trials):
    robot = system_factory(ROBOT)
    odom, plans = robot.topic(Float64, "/odom"), robot.topic(UInt64, "/plan")
    plans.wait_count(5, timeout=10)

    def trial(t):
        [lost] = robot.inject(Drop("/odom", 2.0, probability=0.5, subscribers=["/planner"]))
        # The planner plans once per odometry message it gets: about 10 Hz
        # while half are lost; odometry itself, seen from outside, is untouched.
        planned = rate(plans, lost.start_ns, lost.end_ns)
        assert 5.0 <= planned <= 15.0, f"{planned:.1f} plans/s with half the odometry lost"
        assert rate(odom, lost.start_ns, lost.end_ns) >= 18.0
        assert lost.counts["dropped"] > 0
        plans.wait_count(len(plans) + 10, timeout=5)  # back to every message
        return {"plans": Measure(planned, "Hz")}

    system_trials(robot, trial, fault="half the planner's odometry lost for 2 s",
                  claim="the planner plans on every odometry message it still gets, ~10 Hz",
                  quick=3, at_least=0.99)  # fmt: skip


def test_late_odometry_delays_the_plans_by_as_much(system_factory, system_trials):
    robot = system_factory(ROBOT)
    plans = robot.topic(UInt64, "/plan")
    plans.wait_count(5, timeout=10)

    def trial(t):
        [late] = robot.inject(Delay("/odom", 1.0, delay_s=0.3, subscribers=["/planner"]))
        plans.wait_count(len(plans) + 10, timeout=5)
        # At its start no plan comes for the 300 ms the first late message
        # is held; then the plans come at the odometry's rate again.
        gap = longest_gap(plans, late.start_ns, late.end_ns)
        assert 0.25 <= gap <= 0.4, f"the plans stopped for {gap:.3f} s"
        assert rate(plans, late.start_ns + 400_000_000, late.end_ns) >= 15.0
        return {"longest gap in plans": gap * 1e3}

    system_trials(robot, trial, fault="the planner's odometry 300 ms late for 1 s",
                  claim="the plans pause for the delay, then keep the odometry's rate",
                  quick=3, at_least=0.99)  # fmt: skip
