"""Each node's figures on /diagnostics (container/diagnostics.py): its
unique_id and pid, and in isolated mode its memory in use and budget as the
allocator guard counts them, a WARN once it nears its budget."""

from __future__ import annotations

import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from std_msgs.msg import UInt64

from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness.system import NodeSpec

MiB = 1 << 20
ODOMETRY = NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 20.0})
# Holds 59 steps, then stops: over 90% of a 64 MiB budget (57.6 MiB)
# whatever else its process holds (in the per-node profile, its
# participant: ~2 MiB more), and not over it. A step is a bytearray just
# under 1 MiB, so that its block is 1 MiB under either allocator (1 MiB and
# a header would be jemalloc's next size class, 1.25 MiB: 74 MiB in all).
STEP = MiB - 4096
HELD = 59 * STEP
HOLDER = NodeSpec(TESTRIG, "faults::MemoryLeak", name="holder",
                  parameters={"kind": "bytes", "step": STEP, "steps": 59, "period": 0.01})  # fmt: skip


def _latest(array_recorder, names: set[str], timeout: float = 15.0) -> dict[str, DiagnosticStatus]:
    """The statuses, by node, of the first array that has all ``names``."""
    got = array_recorder.wait_for(
        lambda a: names <= {s.name.split(": ", 1)[1] for s in a.status}, timeout, f"statuses of {sorted(names)}"
    )
    return {s.name.split(": ", 1)[1]: s for s in got.status}


def _values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


def test_isolated_nodes_show_their_memory_and_budget(system_factory):
    robot = system_factory([ODOMETRY, HOLDER], ["--isolated", "--node-memory-limit", "64M"])
    diagnostics = robot.topic(DiagnosticArray, "/diagnostics")
    robot.topic(UInt64, "/holder/held").wait_for(lambda m: m.data == HELD, 15, "59 MiB held")
    diagnostics.wait_count(len(diagnostics) + 2, timeout=5)  # an array made after it held them
    statuses = _latest(diagnostics, {"/odometry", "/holder"})
    for name, status in statuses.items():
        values = _values(status)
        running = robot.node(name)
        assert status.name == f"/ComponentManager: {name}" and status.hardware_id == "/ComponentManager"
        assert (values["unique_id"], values["pid"]) == (str(running.unique_id), str(running.pid))
        assert int(values["memory_limit_bytes"]) == 64 * MiB
    holder, odometry = _values(statuses["/holder"]), _values(statuses["/odometry"])
    assert HELD <= int(holder["memory_in_use_bytes"]) < 64 * MiB
    assert statuses["/holder"].level == DiagnosticStatus.WARN
    assert statuses["/holder"].message.startswith("near its memory budget: ")
    assert 0 < int(odometry["memory_in_use_bytes"]) < 32 * MiB
    assert statuses["/odometry"].level == DiagnosticStatus.OK
    # The harness's view of the same (System.memory, the report's memory
    # strips): the holder's samples in order, the last holding what it
    # holds, under its budget.
    held = robot.memory("/holder")
    assert [s.at_ns for s in held] == sorted(s.at_ns for s in held)
    assert held[-1].in_use >= HELD and {s.limit for s in held} == {64 * MiB}
    assert robot.memory("/odometry")
    with pytest.raises(KeyError, match="no node '/nobody'"):  # a typo, not "no samples"
        robot.memory("/nobody")


@pytest.mark.parametrize("args", [[], ["--isolated", "--no-alloc-guard"]], ids=["threads", "no-alloc-guard"])
def test_where_nothing_counts_memory_a_node_shows_its_ids_only(system_factory, args):
    robot = system_factory([ODOMETRY], args)
    status = _latest(robot.topic(DiagnosticArray, "/diagnostics"), {"/odometry"})["/odometry"]
    assert set(_values(status)) == {"unique_id", "pid"} and status.level == DiagnosticStatus.OK
    assert robot.memory("/odometry") == []


def test_a_node_leaves_the_diagnostics_at_its_unload(system_factory):
    robot = system_factory([ODOMETRY], ["--isolated"])
    diagnostics = robot.topic(DiagnosticArray, "/diagnostics")
    _latest(diagnostics, {"/odometry"})
    assert robot.client.unload(robot.node("/odometry").unique_id).success
    diagnostics.wait_for(lambda a: not a.status, 5, "an array without the unloaded node")


def test_the_period_is_the_diagnostic_updater_parameter_read_once_at_start(system_factory):
    """``diagnostic_updater.period`` (its name in ROS's diagnostic_updater)
    on the container's command line: the arrays come that often (their
    stamps, the container's clock); set later, it is refused."""
    from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
    from rcl_interfaces.srv import SetParameters

    robot = system_factory([ODOMETRY], ["--ros-args", "-p", "diagnostic_updater.period:=0.1"])
    diagnostics = robot.topic(DiagnosticArray, "/diagnostics")
    diagnostics.wait_count(12, timeout=10)
    stamps = sorted(a.header.stamp.sec + a.header.stamp.nanosec / 1e9 for a in diagnostics.messages())
    apart = sorted(b - a for a, b in zip(stamps, stamps[1:], strict=False))
    assert 0.05 <= apart[len(apart) // 2] <= 0.25, apart  # the default's would be 1 s
    value = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=2.0)
    request = SetParameters.Request(parameters=[Parameter(name="diagnostic_updater.period", value=value)])
    [result] = robot.call(SetParameters, "/ComponentManager/set_parameters", request).results
    assert not result.successful and "read-only" in result.reason


@pytest.mark.parametrize("value", ["0", "-1.0", "abc", "true"])
def test_a_period_that_is_not_seconds_above_0_stops_the_start_saying_so(container_factory, value):
    proc = container_factory.start(["--ros-args", "-p", f"diagnostic_updater.period:={value}"])
    assert proc.wait(timeout=30) == 1
    said = "component_container: diagnostic_updater.period is the seconds between two /diagnostics publications, not "
    assert said in proc.log_text(), proc.log_text()[-2000:]
