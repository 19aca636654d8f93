"""Faults a user's System gets from outside beyond a signal: CPU
starvation in a cgroup of the harness's own (cpu_starve.py), and fault
schedules (schedule.py)."""

import os
import random
import subprocess
import sys
import time
from typing import Any

import pytest

from cloneguard.harness import cpu_starve
from cloneguard.harness.cpu_starve import CpuStarve, CpuStarveUnavailable, quota_and_period
from cloneguard.harness.schedule import At, Freeze, Kill, ScheduledFault, Starve, random_over, run_schedule, sequence
from cloneguard.harness.system import Fault, NodeSpec, rate


def _starve_or_skip():
    try:
        cpu_starve._hierarchy()
    except CpuStarveUnavailable as exc:
        pytest.skip(f"no CPU starvation on this machine: {exc}")


@pytest.mark.parametrize(
    "cpus, quota, period",
    [(0.001, 1000, 1_000_000), (0.005, 5000, 1_000_000), (0.5, 50_000, 100_000), (2, 200_000, 100_000)],
)
def test_a_quota_in_cpus_is_microseconds_of_a_period(cpus, quota, period):
    assert quota_and_period(cpus) == (quota, period)


@pytest.mark.parametrize("cpus", [0, 0.0005, -1, 2000])
def test_a_quota_out_of_range_is_refused(cpus):
    with pytest.raises(ValueError, match="0.001-1024 CPUs"):
        quota_and_period(cpus)


SPINNER = """
import time
n = 0
while True:
    n += 1
    if n % 20000 == 0:
        print(n, time.monotonic(), flush=True)
"""


def _spins_per_s(proc, seconds: float) -> float:
    first = last = None
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        line = proc.stdout.readline().split()
        last = (int(line[0]), float(line[1]))
        first = first or last
    assert first is not None and last is not None, f"no line from the spinner within {seconds:g} s"
    return (last[0] - first[0]) / max(last[1] - first[1], 1e-6)


def test_a_starved_process_runs_at_its_quota_then_goes_home():
    _starve_or_skip()
    proc = subprocess.Popen([sys.executable, "-c", SPINNER], stdout=subprocess.PIPE, text=True)
    try:
        home = cpu_starve._current(proc.pid, cpu_starve._hierarchy()[0])
        free = _spins_per_s(proc, 1.0)
        with CpuStarve(proc.pid, 0.05) as starve:
            assert cpu_starve._current(proc.pid, starve.kind) == "/" + starve.dir.name
            starved = _spins_per_s(proc, 2.0)
        assert starved < 0.25 * free, (starved, free)  # ~5% of a core against ~100%
        assert cpu_starve._current(proc.pid, starve.kind) == home
        assert not starve.dir.exists()
    finally:
        proc.kill()
        proc.wait()


def test_a_process_that_dies_starved_leaves_no_cgroup():
    _starve_or_skip()
    proc = subprocess.Popen([sys.executable, "-c", SPINNER], stdout=subprocess.PIPE, text=True)
    with CpuStarve(proc.pid, 0.01) as starve:
        proc.kill()
        proc.wait()
    assert not starve.dir.exists()


def test_schedules_are_data_a_trials_random_replays():
    faults: list[ScheduledFault] = [Kill("/a"), Freeze("/b", 0.5), Starve("/c", 0.01, 1.0)]
    one, two = (random_over(random.Random(7), 3.0, faults, count=4) for _ in range(2))
    assert one == two and [a.seconds for a in one] == sorted(a.seconds for a in one)
    assert all(0 <= a.seconds <= 3.0 and a.fault in faults for a in one)
    assert sequence(*faults, every_s=0.5, first_s=0.1) == [At(0.1, faults[0]), At(0.6, faults[1]), At(1.1, faults[2])]
    with pytest.raises(ValueError):
        At(-1, faults[0])


def test_a_schedule_takes_a_fault_an_at_or_a_list_of_both():
    from cloneguard.harness.schedule import as_schedule

    kill, freeze = Kill("/a"), Freeze("/b", 0.5)
    assert as_schedule(kill) == [At(0.0, kill)]
    assert as_schedule(At(1.0, freeze)) == [At(1.0, freeze)]
    assert as_schedule([At(1.0, freeze), kill]) == [At(0.0, kill), At(1.0, freeze)]
    with pytest.raises(TypeError, match="not str"):
        as_schedule(["/a"])  # type: ignore[list-item]  # the wrong type is the point


class _Recording:
    """A stand-in System that records what run_schedule asks of it."""

    def __init__(self):
        self.faults = []

    def kill(self, node, sig):
        now = time.monotonic_ns()
        self.faults.append(Fault(node, "SIGKILL", now, now))

    def freeze(self, node, seconds):
        start = time.monotonic_ns()
        time.sleep(seconds)
        self.faults.append(Fault(node, f"freeze {seconds:g} s", start, time.monotonic_ns()))

    def starve(self, node, cpus, seconds):
        raise CpuStarveUnavailable("not here")


def test_a_schedule_runs_at_its_times_and_lasting_faults_overlap():
    system: Any = _Recording()  # what run_schedule asks of a System
    t0 = time.monotonic_ns()
    done = run_schedule(system, [At(0.3, Kill("/b")), At(0.0, Freeze("/a", 0.6))])
    by_node = {f.node: f for f in done}
    assert by_node["/a"].start_ns < by_node["/b"].start_ns < by_node["/a"].end_ns  # the kill during the freeze
    assert (by_node["/b"].start_ns - t0) / 1e9 == pytest.approx(0.3, abs=0.1)
    with pytest.raises(CpuStarveUnavailable):  # an error is raised once every fault has ended
        run_schedule(system, [At(0.0, Starve("/c", 0.01, 1.0)), At(0.1, Kill("/d"))])
    assert system.faults[-1].node == "/d"


ROBOT = [NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 50.0})]


def test_odometry_starved_slows_down_and_recovers(system_factory):
    _starve_or_skip()
    from std_msgs.msg import Float64

    robot = system_factory(ROBOT)
    odom = robot.topic(Float64, "/odom")
    odom.wait_count(20, timeout=10)
    before = time.monotonic_ns()
    odom.wait_count(len(odom) + 25, timeout=10)
    free = rate(odom, before)
    start, end = robot.starve("/odometry", 0.001, 2.0)
    odom.wait_count(len(odom) + 25, timeout=10)
    assert rate(odom, start, end) < 0.5 * free, (rate(odom, start, end), free)
    assert rate(odom, end) > 0.7 * free
    [fault] = robot.faults
    assert fault.what == "starve 0.001 CPU 2 s" and not fault.ends_the_node
    pid = robot.node("/odometry").pid
    assert not any("cloneguard-harness" in line for line in open(f"/proc/{pid}/cgroup"))
    assert os.path.exists(f"/proc/{pid}")
