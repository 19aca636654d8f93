"""The container's memory watch (isolated/clonecore/memwatch.c, memory_watch.py):
before the container's memory reaches what its memory cgroup lets it use,
it ends the node process that uses the most (weighed by its
``cloneguard.oom_score_adj``), alone; the kernel's OOM killer, which would
end every process of the shared address space, never comes.

Every container here runs in a memory cgroup the test made with a limit
(harness/memory_cgroup.py), never against the machine's memory; the nodes
have no budgets of their own.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys

import pytest
from std_msgs.msg import Float64, UInt64

from cloneguard.container.isolated.memory_watch import MIN_MARGIN
from cloneguard.container.memory_budget import OOM_SCORE_ADJ
from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness.memory_cgroup import MemoryCgroup, MemoryCgroupUnavailable
from cloneguard.harness.system import NodeSpec, longest_gap

MiB = 1 << 20
CGROUP_LIMIT = 768 * MiB
ODOMETRY = NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 50.0})
ENDED = re.compile(
    r"out of memory: the container used (?P<used>[\d.]+) MiB of the (?P<limit>[\d.]+) MiB it may use, "
    r"and this node process the most: (?P<node>[\d.]+) MiB"
)


def _memory_node(name: str, kind: str, step: int, steps: int = 0, adj: int | None = None) -> NodeSpec:
    """A MemoryLeak: for ever (steps 0), or until it holds steps x step."""
    extra = {OOM_SCORE_ADJ: adj} if adj is not None else {}
    params = {"kind": kind, "step": step, "steps": steps, "delay": 1.0}
    return NodeSpec(TESTRIG, "faults::MemoryLeak", name=name, parameters=params, extra_arguments=extra)


@pytest.fixture
def limited(limited_system):
    """system_factory, each container in a memory cgroup of CGROUP_LIMIT."""
    return lambda nodes, container_args: limited_system(nodes, container_args, CGROUP_LIMIT)


def _ended_by_the_watch(robot, name: str) -> re.Match:
    crashed = robot.wait_crashed(name, timeout=60)
    assert crashed.exit_signal == signal.SIGKILL
    said = ENDED.search(crashed.error_message)
    assert said, crashed.error_message
    assert float(said["limit"]) == CGROUP_LIMIT / MiB
    assert CGROUP_LIMIT - MIN_MARGIN - 8 * MiB <= float(said["used"]) * MiB < CGROUP_LIMIT
    return said


@pytest.mark.parametrize(
    "kind, step",
    [("bytes", 8 * MiB), ("native", 8 * MiB), ("python", 2 * MiB)],
    ids=["bytearray", "malloc", "python-objects"],
)
@pytest.mark.parametrize("args", [["--isolated", "--profile", "per-node", "--allocator", "glibc"],
                                  ["--isolated", "--profile", "shared", "--allocator", "glibc"],
                                  ["--isolated", "--allocator", "jemalloc"]],
                         ids=["per-node", "shared", "jemalloc"])  # fmt: skip
def test_a_leak_that_would_fill_the_container_ends_the_leaking_node_alone(limited, args, kind, step):
    robot = limited([ODOMETRY, _memory_node("leak", kind, step)], args)
    odom = robot.topic(Float64, "/odom")
    held = robot.topic(UInt64, "/leak/held")
    odom.wait_count(10, timeout=10)
    said = _ended_by_the_watch(robot, "/leak")
    # The leaking node held most of what the container used.
    assert held.messages() and float(said["node"]) * MiB >= held.messages()[-1].data * 0.9
    odom.wait_count(len(odom) + 50, timeout=10)
    assert longest_gap(odom, odom.items()[0].at_ns) < 1.0
    assert robot.alive()
    assert robot.proc.memory_cgroup.oom_kills() == 0
    # The dead leak's memory is still in the container, near the trigger:
    # that ended no other node.
    assert [e.full_node_name for e in robot.client.events.messages() if e.event_type == 3] == ["/leak"]


@pytest.mark.parametrize("protected", [False, True], ids=["biggest-ended", "biggest-protected"])
def test_the_node_that_uses_the_most_is_ended_unless_it_is_protected(limited, protected):
    # /holder keeps 400 MiB; /leak, loaded once it does, grows until the
    # container nears its limit, by then holding less than /holder (loaded
    # together, a busy machine once let the leak outgrow a slow holder).
    holder = _memory_node("holder", "bytes", 40 * MiB, steps=10, adj=-1000 if protected else None)
    robot = limited([ODOMETRY, holder], ["--isolated"])
    robot.topic(UInt64, "/holder/held").wait_for(lambda m: m.data == 400 * MiB, timeout=30, what="400 MiB held")
    robot.load(_memory_node("leak", "bytes", 4 * MiB))
    ended, spared = ("/leak", "/holder") if protected else ("/holder", "/leak")
    _ended_by_the_watch(robot, ended)
    assert os.path.exists(f"/proc/{robot.node(spared).pid}")
    assert robot.alive()
    assert robot.proc.memory_cgroup.oom_kills() == 0
    assert [e.full_node_name for e in robot.client.events.messages() if e.event_type == 3] == [ended]


def test_bad_scores_are_refused_at_once_and_the_container_serves_on(system_factory):
    robot = system_factory([ODOMETRY], ["--isolated"])
    for bad, says in [(1001, "must be from -1000 to 1000"), (-2000, "must be from -1000 to 1000"),
                      ("high", "must be an integer")]:  # fmt: skip
        answer = robot.client.load(TESTRIG, "faults::MemoryLeak", extra_arguments={OOM_SCORE_ADJ: bad}, timeout=5)
        assert not answer.success and says in answer.error_message, answer.error_message
    answer = robot.client.load(TESTRIG, "faults::MemoryLeak", extra_arguments={OOM_SCORE_ADJ: -1000})
    assert answer.success, answer.error_message


def test_a_score_in_thread_mode_is_refused(system_factory):
    robot = system_factory([ODOMETRY], [])
    answer = robot.client.load(TESTRIG, "faults::MemoryLeak", extra_arguments={OOM_SCORE_ADJ: 100}, timeout=5)
    assert not answer.success and "needs an isolated container" in answer.error_message


def test_the_watch_finds_the_limit_of_the_cgroup_it_runs_in():
    try:
        cgroup = MemoryCgroup(CGROUP_LIMIT)
    except MemoryCgroupUnavailable as why:
        pytest.skip(f"no memory cgroup can be made here: {why}")
    probe = "from cloneguard.container.isolated.memory_watch import find; l = find(); print(l.limit, l.where)"
    try:
        out = subprocess.run(
            ["sh", "-c", f'echo $$ > {cgroup.procs} && exec "$0" -c "$1"', sys.executable, probe],
            capture_output=True, text=True, check=True, timeout=30,
        ).stdout.split(maxsplit=1)  # fmt: skip
    finally:
        cgroup.close()
    assert int(out[0]) == CGROUP_LIMIT
    assert cgroup.dir.name in out[1], out


def test_the_watch_runs_on_a_real_time_monitor_and_the_log_says_so(system_factory):
    """The memory watch looks from the monitor thread, which a container
    run as root makes real-time (under a full load an ordinary one was seen
    24 MiB late of a 64 MiB margin); its node processes keep the ordinary
    policy."""
    if os.geteuid() != 0:
        pytest.skip("SCHED_FIFO needs root or CAP_SYS_NICE")
    robot = system_factory([ODOMETRY], ["--isolated"])
    assert "monitor thread: real-time (SCHED_FIFO 1)" in robot.log_text()
    tasks = f"/proc/{robot.proc.pid}/task"
    [monitor] = [int(t) for t in os.listdir(tasks) if open(f"{tasks}/{t}/comm").read().strip() == "cg-monitor"]
    assert os.sched_getscheduler(monitor) == os.SCHED_FIFO | os.SCHED_RESET_ON_FORK
    assert os.sched_getscheduler(robot.node("/odometry").pid) == os.SCHED_OTHER
