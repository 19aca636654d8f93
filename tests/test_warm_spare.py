"""The per-node profile's warm spare (container/isolated/spare.py), seen from
outside: the container's child processes, the LOADED events' pids, the
graph and the log."""

import os
import signal
import time

import pytest
from cloneguard_interfaces.msg import ComponentEvent
from slow_load import SlowLoad
from std_msgs.msg import UInt64

from cloneguard.container.isolated.cgroups import cgroup2_mount
from cloneguard.harness import procfs
from cloneguard.harness.rest import SPARE_PLACEHOLDER as PLACEHOLDER

PKG = "cloneguard"


def wait_until(pred, timeout: float = 10.0, what: str = "condition"):
    """Bounded poll for what only /proc and the graph show."""
    deadline = time.monotonic() + timeout
    while True:
        value = pred()
        if value:
            return value
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def the_spare(container, not_pids=()) -> int:
    """The pid of the container's one child that is no node's (waits for it)."""

    def one():
        spares = [p for p in procfs.children_of(container.pid) if p not in not_pids]
        return spares[0] if len(spares) == 1 else None

    return wait_until(one, what="the spare process")


def placeholders(client) -> set[str]:
    return {name for name, _ns in client.node.get_node_names_and_namespaces() if name.startswith(PLACEHOLDER)}


def loaded_pid(client, unique_id) -> int:
    return client.wait_for_event(ComponentEvent.LOADED, unique_id=unique_id).pid


@pytest.mark.parametrize("container_args", [["--isolated", "--profile", "per-node"]])
def test_a_load_is_served_by_the_spare_made_ahead_and_another_is_made(client, container):
    spare = the_spare(container)
    # Its placeholder holds the participant; hidden by its leading underscore.
    wait_until(lambda: f"{PLACEHOLDER}{spare}" in placeholders(client), what="the spare's placeholder node")
    stat = procfs.stat(spare)
    assert stat is not None and stat.comm == "cg-node"  # not "cg-monitor", the thread it was cloned from
    uid = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="hb").unique_id
    assert loaded_pid(client, uid) == spare
    client.subscribe(UInt64, "/hb/heartbeat").wait_count(3, timeout=10)
    nxt = the_spare(container, not_pids={spare})
    assert nxt != spare
    wait_until(
        lambda: placeholders(client) == {f"{PLACEHOLDER}{nxt}"}, what="only the new spare's placeholder in the graph"
    )
    # Placeholders have no services, so none is left behind in the node's process.
    assert not [name for name, _ in client.node.get_service_names_and_types() if PLACEHOLDER in name]
    # An unloaded node's process goes; the spare stays for the next load.
    assert client.unload(uid).success
    assert procfs.children_of(container.pid) == [nxt]
    assert loaded_pid(client, client.load_ok(PKG, "cloneguard::Heartbeat", node_name="hb2").unique_id) == nxt


@pytest.mark.parametrize("container_args", [["--isolated", "--profile", "per-node"]])
def test_a_load_that_needs_a_context_of_its_own_leaves_the_spare_alone(client, container):
    spare = the_spare(container)
    uid = client.load_ok(PKG, "cloneguard::Heartbeat", extra_arguments={"forward_global_arguments": True}).unique_id
    pid = loaded_pid(client, uid)
    assert pid != spare
    assert sorted(procfs.children_of(container.pid)) == sorted([spare, pid])


@pytest.mark.parametrize("container_args", [["--isolated", "--profile", "per-node"]])
def test_a_spare_killed_from_outside_is_replaced_at_the_next_load(client, container):
    spare = the_spare(container)
    os.kill(spare, signal.SIGKILL)
    wait_until(lambda: f"(pid {spare}) ended: killed by SIGKILL" in container.log_text(), what="the log line")
    assert procfs.children_of(container.pid) == []
    uid = client.load_ok(PKG, "cloneguard::Heartbeat").unique_id
    pid = loaded_pid(client, uid)
    assert pid != spare and container.alive()
    assert client.list() == [(uid, "/heartbeat")]
    the_spare(container, not_pids={pid})


def test_a_failed_construction_in_the_spare_answers_and_a_new_spare_is_made(container_factory, misfit_env):
    container = container_factory.start(["--isolated", "--profile", "per-node"], extra_env=misfit_env)
    client = container_factory.connect(container)
    spare = the_spare(container)
    resp = client.load("misfit-components", "misfits::Raises")
    assert not resp.success and "sensor not found" in resp.error_message
    wait_until(lambda: procfs.stat(spare) is None, what="the used spare to end")
    nxt = the_spare(container)
    assert nxt != spare
    assert loaded_pid(client, client.load_ok(PKG, "cloneguard::Heartbeat").unique_id) == nxt


@pytest.mark.parametrize(
    "container_args",
    [
        ["--isolated", "--profile", "per-node", "--no-warm-spare"],
        ["--isolated", "--profile", "shared"],
        ["--isolated"],
        pytest.param(
            ["--isolated", "--profile", "per-node", "--cgroups"],
            marks=pytest.mark.skipif(cgroup2_mount() is None, reason="no cgroup2 here"),
        ),
    ],
    ids=["no-warm-spare", "shared", "default", "cgroups"],
)
def test_no_spare_is_kept_when_switched_off_in_the_shared_profile_or_with_cgroups(client, container):
    # With --cgroups each node's process is born in its cgroup: none is made ahead.
    uid = client.load_ok(PKG, "cloneguard::Heartbeat").unique_id
    pid = loaded_pid(client, uid)
    client.subscribe(UInt64, "/heartbeat/heartbeat").wait_count(3, timeout=10)
    assert procfs.children_of(container.pid) == [pid]
    assert placeholders(client) == set()


def test_the_spare_switch_needs_isolated_mode(container_factory):
    proc = container_factory.start(["--no-warm-spare"])
    assert proc.wait(timeout=20) != 0
    assert "--no-warm-spare needs --isolated" in proc.log_text()


@pytest.mark.parametrize("container_args", [["--isolated", "--profile", "per-node", "--no-warm-spare"]])
def test_every_node_process_makes_its_participant_through_a_placeholder(client, container):
    # Not only the spare: a node process's participant is made (and, after
    # a failed construction, deleted) by its placeholder, off the GIL; the
    # placeholder goes once the node is built.
    slow = SlowLoad(client, seconds=2.0)
    [pid] = procfs.children_of(container.pid)
    assert placeholders(client) == {f"{PLACEHOLDER}{pid}"}, "no placeholder while the node is built"
    answer = slow.answer()
    assert answer.success, answer
    assert loaded_pid(client, answer.unique_id) == pid
    wait_until(lambda: placeholders(client) == set(), what="the placeholder to go once the node is built")
