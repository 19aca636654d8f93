"""Memory budgets of node processes (container/memory_budget.py, the
allocator guard's count: isolated/allocguard/allocguard.c, pyalloc.c, bigblocks.c).

A node that leaks is ended alone, just before the allocation that would
take it over its budget, its CRASHED saying so; the rest go on. Every
container here that a leak could fill runs in a memory cgroup the test
made (harness/memory_cgroup.py), with room for the budgets and little more,
never against the machine's memory.
"""

from __future__ import annotations

import re
import signal

import pytest
from std_msgs.msg import Float64, UInt64

from cloneguard.container.memory_budget import MEMORY_LIMIT, parse_size
from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness.memory_cgroup import MemoryCgroup, MemoryCgroupUnavailable
from cloneguard.harness.system import NodeSpec, longest_gap

MiB = 1 << 20
#: The cgroup each container here runs in: the budgets below and the
#: container's own memory fit, a leak past them does not.
CGROUP_LIMIT = 1536 * MiB
BUDGET = 200 * MiB

ODOMETRY = NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 50.0})


def _leak(kind: str, step: int, budget: int | None = None, **params) -> NodeSpec:
    """A MemoryLeak that starts a second after its load (the odometry is
    recorded by then)."""
    extra = {MEMORY_LIMIT: f"{budget // MiB}M"} if budget is not None else {}
    params = {"kind": kind, "step": step, "delay": 1.0, **params}
    return NodeSpec(TESTRIG, "faults::MemoryLeak", parameters=params, extra_arguments=extra)


LEAK = "/memory_leak"


@pytest.fixture
def limited(limited_system):
    """system_factory, each container in a memory cgroup of CGROUP_LIMIT."""
    return lambda nodes, container_args: limited_system(nodes, container_args, CGROUP_LIMIT)


OVER = re.compile(
    r"out of memory: (?P<used>[\d.]+) MiB in use, over its limit of (?P<limit>[\d.]+) MiB "
    r"\(it asked for (?P<asked>[\d.]+) (?P<unit>[KM])iB more\)"
)


@pytest.mark.parametrize(
    "kind, step",
    [("bytes", 8 * MiB), ("native", 8 * MiB), ("python", 2 * MiB)],
    ids=["bytearray", "malloc", "python-objects"],
)
@pytest.mark.parametrize("args", [["--isolated", "--profile", "per-node", "--allocator", "glibc"],
                                  ["--isolated", "--allocator", "glibc"], ["--isolated", "--allocator", "jemalloc"],
                                  ["--isolated", "--profile", "per-node", "--allocator", "jemalloc"]],
                         ids=["per-node", "shared", "jemalloc", "jemalloc-per-node"])  # fmt: skip
def test_a_leaking_node_is_ended_alone_at_its_budget(limited, args, kind, step):
    robot = limited([ODOMETRY, _leak(kind, step)], [*args, "--node-memory-limit", f"{BUDGET // MiB}M"])
    odom = robot.topic(Float64, "/odom")
    held = robot.topic(UInt64, f"{LEAK}/held")
    odom.wait_count(10, timeout=10)
    crashed = robot.wait_crashed(LEAK, timeout=60)
    assert crashed.exit_signal == signal.SIGKILL
    said = OVER.search(crashed.error_message)
    assert said, crashed.error_message
    used, limit, asked = (float(said[k]) for k in ("used", "limit", "asked"))
    asked /= 1024 if said["unit"] == "K" else 1
    assert limit == pytest.approx(BUDGET / MiB)
    assert used + asked > limit - 0.05 and limit >= used  # ended before the allocation that went over (0.1 MiB shown)
    # It had leaked about its budget: what it said it held, less what the
    # node process had before (its participant, its modules' objects).
    assert held.messages() and held.messages()[-1].data <= BUDGET
    assert held.messages()[-1].data >= BUDGET / 2, held.messages()[-1].data
    # The rest went on throughout, the container too, and the kernel's OOM
    # killer never stepped in.
    odom.wait_count(len(odom) + 50, timeout=10)
    assert longest_gap(odom, odom.items()[0].at_ns) < 1.0
    assert robot.alive()
    assert robot.proc.memory_cgroup.oom_kills() == 0


def test_a_death_logs_what_the_node_had_in_use(system_factory):
    """Any death, not only one for memory: the log line says what the
    guard counted of the node process when it died."""
    step = MiB - 4096  # a 1 MiB block under either allocator
    holder = _leak("bytes", step, budget=64 * MiB, steps=30, period=0.01, delay=0.0)
    robot = system_factory([holder], ["--isolated"])
    robot.topic(UInt64, f"{LEAK}/held").wait_for(lambda m: m.data == 30 * step, 15, "30 MiB held")
    pid = robot.node(LEAK).pid
    robot.kill(LEAK, signal.SIGKILL)
    robot.wait_crashed(LEAK)
    said = robot.wait_for_log(
        rf"{LEAK} \(unique_id \d+, pid {pid}\) died: .* \((?P<used>[\d.]+) MiB in use of its 64.0 MiB budget\)",
        timeout=10,
    )
    assert 30 * step / MiB <= float(said["used"]) < 64


def test_a_nodes_own_budget_wins_over_the_containers(limited):
    robot = limited([ODOMETRY, _leak("bytes", 4 * MiB, budget=64 * MiB)], ["--isolated", "--node-memory-limit", "1G"])
    said = OVER.search(robot.wait_crashed(LEAK, timeout=60).error_message)
    assert said and float(said["limit"]) == 64.0
    assert robot.alive()


@pytest.mark.parametrize("allocator", ["glibc", "jemalloc"])
def test_a_leak_whose_malloc_fails_counts_nothing(system_factory, allocator):
    # 2**60 bytes: no allocator can give them; no memory is used.
    robot = system_factory([ODOMETRY, _leak("huge", 1 << 60)], ["--isolated", "--allocator", allocator])
    held = robot.topic(UInt64, f"{LEAK}/held")
    robot.proc.wait_for_log(rf"\[memory_leak\]: malloc\({1 << 60}\) returned NULL: this step leaked nothing", 10)
    assert len(held) == 0 and robot.alive()


def test_without_a_budget_a_node_holds_what_it_needs(limited):
    # The container's default is none: 12 steps of 8 MiB, held, and alive.
    robot = limited([ODOMETRY, _leak("bytes", 8 * MiB, steps=12)], ["--isolated"])
    held = robot.topic(UInt64, f"{LEAK}/held")
    held.wait_for(lambda m: m.data == 96 * MiB, timeout=30, what="96 MiB held")
    assert robot.alive() and not [e for e in robot.client.events.messages() if e.event_type == 3]


def test_bad_budgets_are_refused_at_once_and_the_container_serves_on(system_factory):
    robot = system_factory([ODOMETRY], ["--isolated"])
    for bad, says in [("lots", "a size is bytes or a number with K, M, G or T"), (-5, "at least 0 bytes"),
                      (2.5, "must be an integer or a string")]:  # fmt: skip
        answer = robot.client.load(TESTRIG, "faults::MemoryLeak", extra_arguments={MEMORY_LIMIT: bad}, timeout=5)
        assert not answer.success and says in answer.error_message, answer.error_message
    assert robot.client.load(TESTRIG, "faults::MemoryLeak", extra_arguments={MEMORY_LIMIT: "64M"}).success


@pytest.mark.parametrize("args, says", [([], "needs an isolated container"),
                                        (["--isolated", "--no-alloc-guard"], "needs the allocator guard")])  # fmt: skip
def test_a_budget_where_nothing_counts_memory_is_refused(system_factory, args, says):
    robot = system_factory([ODOMETRY], args)
    answer = robot.client.load(TESTRIG, "faults::MemoryLeak", extra_arguments={MEMORY_LIMIT: "64M"}, timeout=5)
    assert not answer.success and says in answer.error_message, answer.error_message


def test_sizes_read_as_users_write_them():
    assert parse_size("512M") == 512 * MiB and parse_size("1.5G") == 1536 * MiB
    assert parse_size("800MiB") == 800 * MiB and parse_size(4096) == 4096 and parse_size("64k") == 64 << 10
    for bad in ["", "12Q", "M", True, -1]:
        with pytest.raises(ValueError):
            parse_size(bad)


def test_the_harness_memory_cgroup_limits_what_is_in_it():
    try:
        cgroup = MemoryCgroup(64 * MiB)
    except MemoryCgroupUnavailable as why:
        pytest.skip(f"no memory cgroup can be made here: {why}")
    try:
        assert cgroup.usage() == 0 and cgroup.oom_kills() == 0
        limit_file = "memory.limit_in_bytes" if cgroup.kind == "v1" else "memory.max"
        assert int((cgroup.dir / limit_file).read_text()) == 64 * MiB
    finally:
        cgroup.close()
    assert not cgroup.dir.exists()
