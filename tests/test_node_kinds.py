"""Every kind of rclpy node loads, works, unloads and stops cleanly, in
every mode and profile: timers, publishers and subscriptions, services and
clients, action servers and clients, lifecycle nodes in each of their
states, guard conditions, parameter callbacks, callback groups, and the
multi-threaded executor (fixtures/node_kinds.py).

Cleanly: in isolated mode the node's process ends by itself at its unload
(no "did not stop within 500 ms: SIGKILL", no node, executor and
participant "left in memory") and the node leaves the ROS graph (_wait_gone
says how that is seen); a container of them all
ends on SIGTERM by itself, with status 0. Found: a lifecycle node or one
with an action server or client kept its rcl node alive after its unload
(rclpy's destroy_node leaves both to the garbage collector), so its
process never ended and was killed, its participant leaked.
"""

from __future__ import annotations

import os
import signal
import time

import pytest
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy._rclpy_pybind11 import NodeNameNonExistentError
from std_msgs.msg import String
from test_msgs.action import Fibonacci
from test_msgs.srv import BasicTypes

from cloneguard.harness.system import NodeSpec, System

MODES = {
    "threads": [],
    "threads-multi-threaded": ["--use_multi_threaded_executor"],
    "per-node": ["--isolated", "--profile", "per-node"],
    "shared": ["--isolated", "--profile", "shared"],
}
WAIT_S = 15.0
LIFECYCLE_STATES = {  # the state each lifecycle node is unloaded in: the transitions there
    "unconfigured": [],
    "inactive": ["configure"],
    "active": ["configure", "activate"],
    "finalized": ["configure", "activate", "shutdown"],
}
PLAIN = ["Timers", "PubSub", "Services", "Clients", "Actions", "ActionClients", "Guards", "Parameters", "Groups"]
# What shows that the node's entity works, on /kinds/<node>.
SHOWS = {
    "timers": "tick ",
    "pubsub": "back: ping",
    "clients": "got ",
    "action_clients": "result [0, 1, 1, 2, 3, 5]",
    "guards": "guard ",
    "groups": "exclusive got reentrant",
}
# Lines of the container's log that a clean unload or stop never writes.
UNCLEAN = ("SIGKILL", "left in memory", "[ERROR]")


def _specs() -> list[NodeSpec]:
    specs = [NodeSpec("node_kinds", f"kinds::{kind}") for kind in PLAIN]
    specs += [NodeSpec("node_kinds", "kinds::Lifecycle", name=f"life_{state}") for state in LIFECYCLE_STATES]
    return specs


@pytest.fixture
def kinds_system(system_factory, node_kinds_site, monkeypatch, request):
    """All the kinds loaded into one container of the mode asked for."""
    # The container inherits the test's environment: the kinds are loadable.
    monkeypatch.setenv("PYTHONPATH", str(node_kinds_site))
    return system_factory(_specs(), container_args=MODES[request.param])


def _watch(system: System) -> dict[str, object]:
    return {
        name: system.topic(String, f"/kinds/{name}")
        for name in [*SHOWS, "services", "actions", "parameters", *(f"life_{s}" for s in LIFECYCLE_STATES)]
    }


def _use_every_kind(system: System, shown: dict) -> None:
    """Each entity does its job, seen from outside."""
    for name, prefix in SHOWS.items():
        shown[name].wait_for(lambda m, p=prefix: m.data.startswith(p), WAIT_S, f"{name}: {prefix!r}")
    assert system.call(BasicTypes, "/kinds/add_one", BasicTypes.Request(int32_value=41)).int32_value == 42
    outcome = system.send_goal(Fibonacci, "/kinds/fibonacci", Fibonacci.Goal(order=6))
    assert outcome.accepted and outcome.status == 4  # GoalStatus.STATUS_SUCCEEDED
    assert list(outcome.result.sequence) == [0, 1, 1, 2, 3, 5, 8]
    # Feedback the server sent before it discovered the harness's new
    # client is lost (a volatile topic): what arrived is in order and whole.
    seen = [list(f.sequence) for f in outcome.feedback.messages()]
    assert all(s == [0, 1, 1, 2, 3, 5, 8][: len(s)] for s in seen), seen
    assert [len(s) for s in seen] == sorted(set(len(s) for s in seen)), seen
    gain = Parameter(name="gain", value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=2.5))
    answer = system.call(SetParameters, "/parameters/set_parameters", SetParameters.Request(parameters=[gain]))
    assert answer.results[0].successful
    shown["parameters"].wait_for(lambda m: m.data == "gain=2.5", WAIT_S, "the parameter callback")
    for state, transitions in LIFECYCLE_STATES.items():
        node = f"/life_{state}"
        for transition in transitions:
            assert system.change_state(node, transition), f"{node}: {transition} refused"
        assert system.get_state(node) == state
    shown["life_active"].wait_for(lambda m: m.data == "tick", WAIT_S, "an active lifecycle node's tick")


def _graph(system: System) -> set[str]:
    return {ns.rstrip("/") + "/" + name for name, ns in system.client.node.get_node_names_and_namespaces()}


def _endpoints(system: System, full_name: str) -> list:
    """The node's publishers, subscriptions, services and clients in the graph."""
    namespace, _, name = full_name.rpartition("/")
    node = system.client.node
    try:
        return [
            *node.get_publisher_names_and_types_by_node(name, namespace or "/"),
            *node.get_subscriber_names_and_types_by_node(name, namespace or "/"),
            *node.get_service_names_and_types_by_node(name, namespace or "/"),
            *node.get_client_names_and_types_by_node(name, namespace or "/"),
        ]
    except NodeNameNonExistentError:
        return []


def _wait_gone(system: System, running) -> float:
    """Seconds until the unloaded node is gone: in a node process of its own,
    that process ends, and with it its participant, whose every endpoint
    leaves the graph. Its name may stay: the harness's graph cache can take
    the participant's last list of nodes after the participant's removal,
    and keeps it (rmw_dds_common's GraphCache; seen once in 40 runs under
    -n 2, for as long as the harness ran). Where the node shares a
    participant, its name leaves the graph."""
    start = time.monotonic()

    def waiting(what: str) -> bool:
        assert time.monotonic() < start + WAIT_S, f"{running.full_name}: {what} {WAIT_S:g} s after its unload"
        time.sleep(0.01)
        return True

    if running.pid != system.proc.pid and [r.pid for r in system.nodes.values()].count(running.pid) == 1:
        while os.path.exists(f"/proc/{running.pid}") and waiting(f"its process {running.pid} still runs"):
            pass
        while (left := _endpoints(system, running.full_name)) and waiting(f"still in the ROS graph: {left}"):
            pass
    else:
        while running.full_name in _graph(system) and waiting("still in the ROS graph"):
            pass
    return time.monotonic() - start


def _unclean(log: str) -> list[str]:
    return [line for line in log.splitlines() if any(word in line for word in UNCLEAN)]


@pytest.mark.timeout(240)
@pytest.mark.parametrize("kinds_system", list(MODES), indirect=True)
def test_every_kind_of_node_is_used_then_unloads_cleanly(kinds_system):
    system = kinds_system
    shown = _watch(system)
    _use_every_kind(system, shown)
    took = {}
    # Last loaded first: each client goes before its server (an action
    # server unloaded while a goal of its runs aborts that goal, in rclpy's
    # words "Error raised in execute callback").
    for name, running in reversed(list(system.nodes.items())):
        assert name in _graph(system)
        start = time.monotonic()
        answer = system.client.unload(running.unique_id)
        took[name] = time.monotonic() - start
        assert answer.success, answer.error_message
        gone = _wait_gone(system, running)
        print(f"{name}: unload answered in {took[name]:.3f} s, gone from the graph in {gone:.3f} s")
    assert system.client.list() == []
    assert system.alive()
    assert _unclean(system.proc.log_text()) == [], f"unload times: {took}"


@pytest.mark.timeout(240)
@pytest.mark.parametrize("kinds_system", list(MODES), indirect=True)
def test_a_container_of_every_kind_of_node_ends_on_sigterm_by_itself(kinds_system):
    system = kinds_system
    _use_every_kind(system, _watch(system))
    status = system.proc.stop(grace=10.0)
    assert (status.returncode, status.forced) == (0, False), status
    assert _unclean(system.proc.log_text()) == [], f"stopped in {status.stop_seconds:.2f} s"


@pytest.mark.timeout(240)
@pytest.mark.parametrize("kinds_system", ["shared"], indirect=True)
def test_every_kind_works_again_after_a_restart(kinds_system):
    """System.restart() (what seeded trials do after one that failed): the
    services, the action server and the lifecycle nodes of the new
    container answer the harness as the first container's did; the
    lifecycle nodes start over from unconfigured."""
    system = kinds_system
    shown = _watch(system)
    _use_every_kind(system, shown)
    system.restart()
    _use_every_kind(system, shown)


@pytest.mark.timeout(240)
@pytest.mark.parametrize("kinds_system", ["per-node", "shared"], indirect=True)
def test_every_kind_killed_in_use_is_looked_through_and_the_container_goes_on(kinds_system):
    """After each kind's process is SIGKILLed in use (lifecycle nodes in
    every state, action servers and clients, services, timers), the
    container looks through what only the dead node reached
    (container/isolated/reclaim.py) and says what it let go of, with no
    error, and goes on loading nodes."""
    system = kinds_system
    _use_every_kind(system, _watch(system))
    for name, running in list(system.nodes.items()):
        system.kill(name, signal.SIGKILL)
        system.wait_crashed(name)
        said = system.wait_for_log(rf"unique_id {running.unique_id}: (let go of|its memory stays)[^\n]*", WAIT_S)
        assert said[1] == "let go of", said[0]
    errors = [line for line in system.proc.log_text().splitlines() if "[ERROR]" in line and " died: " not in line]
    assert errors == []  # the deaths themselves are errors: nothing else
    ticks = system.topic(String, "/kinds/timers")  # from now on: the dead Timers' are past
    system.load(NodeSpec("node_kinds", "kinds::Timers", name="after"))
    ticks.wait_for(lambda m: m.data.startswith(SHOWS["timers"]), WAIT_S, "the new node's tick")
    assert system.alive()
