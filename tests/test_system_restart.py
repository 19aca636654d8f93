"""System.restart(): a fresh container with the composition loaded again,
and what a caller keeps, topic() recorders and service() clients, going
on. A restart must not leave a DDS participant behind in the harness's
process: seeded trials restart after every trial that fails, and a deep
run of 100 per-node trials that kept each container's client slowed from
3 s to a minute a trial as their participants piled up (72 of them),
until a container's watchdog fired."""

import os

import pytest
from rcl_interfaces.srv import ListParameters
from std_msgs.msg import String

from cloneguard.harness.system import NodeSpec, call_latency

TALKER = NodeSpec("cloneguard", "cloneguard::Talker", parameters={"topic": "/chatter", "period": 0.02})


def _participants() -> int:
    """Fast DDS participants of this process: each runs one event thread."""
    names = []
    for task in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{task}/comm") as f:
                names.append(f.read())
        except FileNotFoundError:  # ended meanwhile
            pass
    return sum(name.startswith("dds.ev") for name in names)


def test_a_restart_keeps_what_the_caller_holds_and_adds_no_participant(system_factory):
    robot = system_factory([TALKER])
    chatter = robot.topic(String, "/chatter")
    params = robot.service(ListParameters, "/talker/list_parameters")
    chatter.wait_count(3, timeout=15)
    first_pid = robot.node("/talker").pid
    before = _participants()
    for _ in range(3):
        robot.restart()
        assert robot.node("/talker").pid != first_pid
        chatter.wait_count(len(chatter) + 3, timeout=15)
        assert chatter.items()[-1].at_ns > robot.started_ns, "the recorder hears the new container's talker"
        call_latency(robot, params, ListParameters.Request(), timeout=15)
    # The System's first client stays (the recorders and service clients
    # are its); each later container's goes when the next one starts.
    assert _participants() <= before + 1


def test_a_second_system_waits_for_the_first_to_stop(system_factory):
    """Both would be /ComponentManager in the test's ROS domain: before,
    the second one's nodes were loaded into the first container."""
    first = system_factory([TALKER])
    with pytest.raises(RuntimeError, match="one running System at a time"):
        system_factory([TALKER], [])
    assert first.stop().returncode == 0
    second = system_factory([TALKER], [])
    second.wait_for_log(r"Loaded cloneguard::Talker as /talker", timeout=5)  # in its own container
    assert first.log_text().count("Loaded cloneguard::Talker") == 1


def test_a_node_loaded_later_joins_the_composition_and_a_restart_loads_it_again(system_factory):
    robot = system_factory([TALKER], ["--isolated"])
    late = NodeSpec("cloneguard", "cloneguard::Talker", name="late", parameters={"topic": "/later", "period": 0.02})
    later = robot.topic(String, "/later")
    running = robot.load(late)
    assert robot.node("/late") == running and running.pid in robot.client.nodes_by_pid()
    later.wait_count(3, timeout=10)
    with pytest.raises(AssertionError, match="nobody::Nothing did not load"):
        robot.load(NodeSpec("cloneguard", "nobody::Nothing"))
    assert robot.specs == (TALKER, late) and set(robot.nodes) == {"/talker", "/late"}  # as it was
    robot.restart()
    assert set(robot.nodes) == {"/talker", "/late"} and robot.node("/late").unique_id == 2
    later.wait_count(len(later) + 3, timeout=10)
