"""A node's CRASHED event published by the clone core itself (herald.c).

In-process: a CloneCore and a real rcl publisher (the container's event
publisher on a node of this process): the herald's bytes, deserialized by
rclpy at a real subscription, are the event; who owns the event between the
monitor's claim and Python's disarm. In a container: the event's fields, once
per death, and what ListNodes and UnloadNode say of a node announced dead.
"""

from __future__ import annotations

import ctypes
import os
import re
import signal
import sys
import threading
import time
from typing import Any

import pytest
from cloneguard_interfaces.msg import ComponentEvent
from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from ros_support import ros_nodes
from test_isolated_core import Recorder, blocked_in, wait_sleeping, wait_until

from cloneguard.container import events
from cloneguard.container.executors import NodesSingleThreadedExecutor
from cloneguard.container.hosting import NodeDeath, ThreadHost
from cloneguard.container.isolated._clonecore import ffi, lib
from cloneguard.container.isolated.core import CloneCore
from cloneguard.container.isolated.core_events import Repair
from cloneguard.container.manager import ComponentManager
from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness.client import HarnessTimeout

PKG = "cloneguard"
PROFILES = [
    pytest.param(["--isolated", "--profile", "per-node"], id="per-node"),
    pytest.param(["--isolated", "--profile", "shared"], id="shared"),
]
TEXT_SIZE = lib.CG_DEATH_TEXT  # the room a death's words have (core.h)


def words(status: int, code: int, repairs: int = 0, alloc: int = 0, stop_signal: int = 0) -> str:
    buf = ffi.new("char[]", TEXT_SIZE)
    lib.cg_describe_death(status, code, repairs, alloc, stop_signal, buf, TEXT_SIZE)
    return ffi.string(buf).decode()


def test_the_words_for_a_death():
    assert words(signal.SIGKILL, os.CLD_KILLED) == "killed by SIGKILL"
    assert words(signal.SIGSEGV, os.CLD_DUMPED) == "killed by SIGSEGV"
    assert words(3, os.CLD_EXITED) == "exited with code 3"
    assert words(-1, 0) == "exited, status unknown"
    assert words(0, os.CLD_EXITED, stop_signal=signal.SIGTERM) == "exited with code 0 after an outside SIGTERM"
    # A timeout alone is no repair; with one, it is named too.
    assert words(9, os.CLD_KILLED, repairs=lib.CG_REPAIR_GIL_TIMEOUT) == "killed by SIGKILL"
    assert words(9, os.CLD_KILLED, repairs=lib.CG_REPAIR_GIL_RELEASED | lib.CG_REPAIR_GIL_TIMEOUT) == (
        "killed by SIGKILL; repaired: GIL_RELEASED, GIL_TIMEOUT"
    )
    assert words(11, os.CLD_KILLED, alloc=lib.CG_ALLOC_FAULTED | lib.CG_ALLOC_QUARANTINED) == (
        "killed by SIGSEGV; it faulted, so its heap may be torn: its arena is quarantined"
    )
    assert words(9, os.CLD_KILLED, alloc=lib.CG_ALLOC_QUARANTINED | lib.CG_ALLOC_PY_ABANDONED) == (
        "killed by SIGKILL; it died inside the allocator: its arena is quarantined; "
        "it died inside Python's object allocator: its pools are abandoned"
    )


@pytest.mark.parametrize("repair", [r for r in Repair if r and r is not Repair.GIL_TIMEOUT], ids=lambda r: r.name)
def test_each_repair_is_named_as_python_names_it(repair):
    assert words(9, os.CLD_KILLED, repairs=int(repair)) == f"killed by SIGKILL; repaired: {repair.name}"


def test_pythons_repairs_are_the_cores():
    """core_events.Repair has exactly repair.h's CG_REPAIRS, name for name
    and bit for bit."""
    core = {}
    for bit in range(32):
        name = lib.cg_repair_name(bit)
        if name != ffi.NULL:
            core[ffi.string(name).decode()] = 1 << bit
    assert core and core == {r.name: int(r) for r in Repair if r}


def test_a_long_text_is_cut_not_overrun():
    buf = ffi.new("char[]", 24)
    n = lib.cg_describe_death(9, os.CLD_KILLED, int(Repair.GIL_RELEASED), 0, 0, buf, 24)
    assert n == 23 and ffi.string(buf).decode() == "killed by SIGKILL; repa"


# -- in-process: the herald on a real publisher ---------------------------------


class Heard:
    """The events one subscription received."""

    def __init__(self):
        self.msgs: list = []
        self.cond = threading.Condition()
        self.publisher = None  # the EventPublisher heard

    def __call__(self, msg) -> None:
        with self.cond:
            self.msgs.append(msg)
            self.cond.notify_all()

    def wait(self, n: int, timeout: float = 10.0) -> list:
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.msgs) >= n, timeout), f"{len(self.msgs)} of {n} events heard"
            return list(self.msgs)


@pytest.fixture
def herald():
    """(core, recorder, heard, spin): a CloneCore whose herald publishes on a
    container-like event publisher, a subscription to it, both in this
    process, spun on a thread."""
    rec, heard = Recorder(), Heard()
    with ros_nodes("herald_test_container", "herald_test_client") as ((container, client), executor):
        pub = events.EventPublisher(container)
        topic = events.EVENTS_TOPIC.replace("~", container.get_fully_qualified_name())
        client.create_subscription(ComponentEvent, topic, heard, events.EVENTS_QOS)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        core = CloneCore(on_event=rec)
        with pub.handle:
            core.start_herald(*pub.publish_from_c())
            heard.publisher = pub
            try:
                yield core, rec, heard
            finally:
                core.close()
        executor.shutdown()
        spinner.join(5)


def _armed_sleeper(core, **fields):
    child = core.spawn(lambda: time.sleep(60))
    wait_sleeping(child)
    assert core.arm_crashed(child, _crashed(pid=child.pid, **fields))
    return child


MARKER = 99
IN_FLIGHT = 32  # herald.c's MAX_IN_FLIGHT


def _only_the_marker_is_heard(core, heard) -> None:
    """An armed child killed after the case under test: its event is the
    one heard (the herald publishes in order, on one reliable writer), so
    the case published none."""
    marker = _armed_sleeper(core, unique_id=MARKER)
    core.kill(marker, signal.SIGKILL)
    assert core.wait(marker, 10).claimed
    assert [m.unique_id for m in heard.wait(1)] == [MARKER]
    core.release(marker)


ARM: dict[str, Any] = {  # what the manager knows of a node at its load
    "unique_id": 42,
    "full_node_name": "/robot/planner_é",  # not ASCII: the bytes go as they are
    "package_name": "my_pkg",
    "plugin_name": "my_pkg::Planner",
    "start_time_ns": 1_764_000_000_123_456_789,
}


def _crashed(**fields: Any) -> ComponentEvent:
    """The CRASHED event the manager arms a node with (ARM's fields, or these)."""
    return events.message(events.CRASHED, **{**ARM, **fields})


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGSEGV])
def test_the_core_publishes_an_armed_childs_crashed_event(herald, sig):
    core, rec, heard = herald
    child = _armed_sleeper(core)
    before = time.time_ns()
    core.kill(child, sig)
    death = core.wait(child, 10)
    rec.wait_for(lambda: death in rec.events)
    assert death.claimed and death.text == f"killed by {sig.name}"
    assert core.crashed_claimed(child)
    assert core.disarm_crashed(child) is False  # too late: it is announced
    (msg,) = heard.wait(1)
    stamp = msg.stamp.sec * 1_000_000_000 + msg.stamp.nanosec
    assert before < stamp < time.time_ns()
    assert (msg.event_type, msg.unique_id, msg.pid) == (ComponentEvent.CRASHED, 42, child.pid)
    assert (msg.full_node_name, msg.package_name, msg.plugin_name) == (
        ARM["full_node_name"],
        ARM["package_name"],
        ARM["plugin_name"],
    )
    assert (msg.error_message, msg.exit_signal, msg.exit_code) == (f"killed by {sig.name}", sig, 0)
    assert (msg.start_time, msg.allocator_quarantined, msg.repaired_state) == (ARM["start_time_ns"], False, "")
    core.release(child)


def _exit_5_later():
    time.sleep(0.3)
    sys.exit(5)


def test_an_exit_is_published_with_its_code(herald):
    core, rec, heard = herald
    child = core.spawn(_exit_5_later)
    assert core.arm_crashed(child, _crashed(pid=child.pid))
    death = core.wait(child, 10)
    assert death.claimed
    (msg,) = heard.wait(1)
    assert (msg.error_message, msg.exit_signal, msg.exit_code) == ("exited with code 5", 0, 5)
    core.release(child)


def _exit_5_holding_the_gil():
    time.sleep(0.3)
    os._exit(5)  # the _exit system call, with the GIL held


def test_a_death_holding_the_gil_is_left_to_python(herald):
    # Where it held the GIL is Python's to say (core.py reads its frame):
    # the core does not announce it.
    core, rec, heard = herald
    child = core.spawn(_exit_5_holding_the_gil)
    assert core.arm_crashed(child, _crashed(pid=child.pid))
    death = core.wait(child, 10)
    rec.wait_for(lambda: death in rec.events)
    assert death.gil_frame and not death.claimed
    assert core.disarm_crashed(child) is True
    core.release(child)
    _only_the_marker_is_heard(core, heard)


def test_a_disarmed_childs_death_is_pythons_to_report(herald):
    core, rec, heard = herald
    child = _armed_sleeper(core)
    assert core.disarm_crashed(child) is True
    assert core.disarm_crashed(child) is True  # twice: still the caller's
    core.kill(child, signal.SIGKILL)
    death = core.wait(child, 10)
    assert not death.claimed and not core.crashed_claimed(child)
    assert death.text == "killed by SIGKILL"  # the words, whoever publishes
    core.release(child)
    _only_the_marker_is_heard(core, heard)


def test_a_child_asked_to_stop_by_its_parent_is_not_announced(herald):
    core, rec, heard = herald
    child = _armed_sleeper(core)
    core.request_stop(child)
    core.kill(child, signal.SIGKILL)
    death = core.wait(child, 10)
    assert not death.claimed and core.disarm_crashed(child) is True
    core.release(child)
    _only_the_marker_is_heard(core, heard)


def test_after_the_herald_stops_every_death_is_pythons(herald):
    core, rec, heard = herald
    child = _armed_sleeper(core)
    core.stop_herald()
    core.stop_herald()  # again: nothing to stop
    core.kill(child, signal.SIGKILL)
    death = core.wait(child, 10)
    assert not death.claimed
    assert core.disarm_crashed(child) is True  # never claimed: still armed
    core.release(child)
    core.start_herald(*heard.publisher.publish_from_c())
    _only_the_marker_is_heard(core, heard)


def test_without_a_herald_an_armed_childs_death_is_pythons():
    # No herald running: the monitor claims nothing, so the event stays
    # armed: taken back by a disarm, or freed by the release (glibc aborts
    # this process on a double free).
    core = CloneCore(on_event=Recorder())
    try:
        for i in range(40):
            child = core.spawn(lambda: time.sleep(60))
            assert core.arm_crashed(child, _crashed(unique_id=i, pid=child.pid))
            core.kill(child, signal.SIGKILL)
            death = core.wait(child, 10)
            assert death is not None and not death.claimed and not core.crashed_claimed(child)
            if i % 2:
                assert core.disarm_crashed(child) is True
            core.release(child)
    finally:
        core.close()


# -- in a container ---------------------------------------------------------------


def _crash(client, sig=signal.SIGKILL, **load):
    uid = client.load_ok(PKG, "cloneguard::Heartbeat", **load).unique_id
    pid = client.wait_for_event(ComponentEvent.LOADED, unique_id=uid).pid
    before = time.time_ns()
    os.kill(pid, sig)
    return uid, pid, before, client.wait_for_event(ComponentEvent.CRASHED, unique_id=uid)


@pytest.mark.parametrize("container_args", PROFILES)
def test_a_crash_in_a_container_is_announced_once_with_every_field(client, container):
    keep = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="keep").unique_id
    uid, pid, before, crashed = _crash(client, node_name="dies")
    loaded = client.wait_for_event(ComponentEvent.LOADED, unique_id=uid)
    names = (crashed.full_node_name, crashed.package_name, crashed.plugin_name)
    assert names == ("/dies", PKG, "cloneguard::Heartbeat")
    assert (crashed.pid, crashed.exit_signal, crashed.exit_code) == (pid, signal.SIGKILL, 0)
    assert (crashed.start_time, crashed.allocator_quarantined) == (loaded.start_time, False)
    assert crashed.error_message.startswith("killed by SIGKILL")  # and what was repaired
    assert before < crashed.stamp.sec * 1_000_000_000 + crashed.stamp.nanosec
    # Gone from the list as soon as its CRASHED is out, and not unloadable.
    assert client.list() == [(keep, "/keep")]
    resp = client.unload(uid)
    assert not resp.success and resp.error_message == f"No node found with unique_id: {uid}"
    # The container's log says it died, once; a later event marks the end of
    # what the crash published: one CRASHED, no UNLOADED.
    container.wait_for_log(re.escape(f"(unique_id {uid}, pid {pid}) died: killed by SIGKILL"), timeout=10)
    assert client.unload(keep).success
    client.wait_for_event(ComponentEvent.UNLOADED, unique_id=keep)
    about_it = [(m.event_type, m.unique_id) for m in client.events.messages() if m.unique_id == uid]
    assert about_it == [(ComponentEvent.LOADED, uid), (ComponentEvent.CRASHED, uid)]


@pytest.mark.parametrize("container_args", PROFILES)
def test_a_crash_is_announced_while_no_python_in_the_container_can_run(client, container):
    victim = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="victim").unique_id
    victim_pid = client.wait_for_event(ComponentEvent.LOADED, unique_id=victim).pid
    # A node that blocks in libc's sleep() holding the GIL: from then on no
    # Python thread of the container runs until it dies. It does so 1 s
    # after it starts to run, when its LoadNode has long been answered (the
    # answer follows the node's start by about a millisecond; with no delay
    # the hog could take the GIL before it).
    hog = client.load_ok(TESTRIG, "faults::HangInCallback", parameters={"delay": 1.0, "mode": "gil"}).unique_id
    hog_pid = client.wait_for_event(ComponentEvent.LOADED, unique_id=hog).pid
    wait_until(lambda: blocked_in(hog_pid), what="the hog asleep holding the GIL")
    os.kill(victim_pid, signal.SIGKILL)
    crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=victim)
    assert crashed.error_message.startswith("killed by SIGKILL")  # and what was repaired
    # It was the core's: the container's Python still cannot answer.
    with pytest.raises(HarnessTimeout):
        client.list(timeout=1.0)
    assert blocked_in(hog_pid)
    os.kill(hog_pid, signal.SIGKILL)  # dies holding the GIL: repaired, Python goes on
    hog_crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=hog)
    assert "repaired: GIL_RELEASED" in hog_crashed.error_message
    assert client.list() == []
    container.wait_for_log(re.escape(f"(unique_id {victim}, pid {victim_pid}) died: killed by SIGKILL"), timeout=10)


def test_a_herald_stuck_in_a_publish_is_left_behind_and_a_new_one_works(herald):
    core, rec, heard = herald
    # A "publish" that never returns (libc's pause(): the herald thread has
    # every signal that could end it blocked), as a publish stuck on a lock
    # of Fast DDS's that a dead node held would be.
    pause = ctypes.cast(ctypes.CDLL(None).pause, ctypes.c_void_p).value
    _, write_death, _ = heard.publisher.publish_from_c()
    core.stop_herald()
    core.start_herald(pause, write_death, 0)
    # Handed to it while fewer than IN_FLIGHT wait (the first hangs in its
    # publish); past that, the deaths are Python's again.
    stuck = [_armed_sleeper(core, unique_id=i) for i in range(IN_FLIGHT + 2)]
    announced = []
    for child in stuck:
        core.kill(child, signal.SIGKILL)
        announced.append(core.wait(child, 10).claimed)
    assert announced == [True] * IN_FLIGHT + [False, False]
    assert core.stop_herald(timeout=0.2) is False
    # The next herald (the fixture's publisher again) has pipe and thread of its own.
    core.start_herald(*heard.publisher.publish_from_c())
    child = _armed_sleeper(core, unique_id=7)
    core.kill(child, signal.SIGKILL)
    assert core.wait(child, 10).claimed
    assert [m.unique_id for m in heard.wait(1)] == [7]
    for c in [*stuck, child]:
        core.release(c)


# -- the manager, with a host that has announced a death -----------------------------


class AnnouncingHost(ThreadHost):
    """Thread mode's host, which also says, for the ids in ``claimed``,
    that it has published their CRASHED itself: what the isolated host
    says between the core's publish and the death reaching the manager."""

    def __init__(self, executor, context, log):
        super().__init__(executor, context, log)
        self.claimed: set[int] = set()
        self.armed: list[int] = []

    def arm_crashed(self, hosted, event):
        assert (event.event_type, event.unique_id) == (ComponentEvent.CRASHED, hosted.unique_id)
        self.armed.append(hosted.unique_id)

    def disarm_crashed(self, hosted):
        return hosted.unique_id not in self.claimed

    def crashed_claimed(self, hosted):
        return hosted.unique_id in self.claimed


def test_the_manager_neither_lists_nor_unloads_a_node_announced_dead_nor_publishes_it_again():
    with ros_nodes("herald_manager", "herald_manager_client", executor_class=NodesSingleThreadedExecutor) as (
        (node, client),
        executor,
    ):
        host = AnnouncingHost(executor, node.context, node.get_logger())
        manager = ComponentManager(node, host)
        heard = Heard()
        topic = events.EVENTS_TOPIC.replace("~", node.get_fully_qualified_name())
        client.create_subscription(ComponentEvent, topic, heard, events.EVENTS_QOS)
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        try:
            ids = []
            for name in ("dead", "alive"):
                request = LoadNode.Request(package_name=PKG, plugin_name="cloneguard::Heartbeat", node_name=name)
                response = manager._load(request, LoadNode.Response(), None)
                assert response.success, response.error_message
                ids.append(response.unique_id)
            dead, alive = ids
            assert host.armed == ids  # each armed once its LOADED was out
            host.claimed.add(dead)
            listed = manager._list(ListNodes.Request(), ListNodes.Response())
            assert list(listed.unique_ids) == [alive]
            refused = manager._unload(UnloadNode.Request(unique_id=dead), UnloadNode.Response())
            assert not refused.success and refused.error_message == f"No node found with unique_id: {dead}"
            # Its death reaches the manager: no second CRASHED. Then one the
            # host did not announce: the manager publishes that one.
            manager.on_death(dead, NodeDeath(pid=1, exit_signal=9, exit_code=0, reason="killed", claimed=True))
            manager.on_death(alive, NodeDeath(pid=2, exit_signal=9, exit_code=0, reason="killed"))
            heard.wait(3)  # LOADED, LOADED, and the one CRASHED
            crashed = [m.unique_id for m in heard.wait(3) if m.event_type == ComponentEvent.CRASHED]
            assert crashed == [alive]
            assert list(manager._list(ListNodes.Request(), ListNodes.Response()).unique_ids) == []
        finally:
            manager.close()
            executor.shutdown()
            spinner.join(5)
