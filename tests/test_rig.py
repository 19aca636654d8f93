"""The scenario rig (harness/rig.py) on a real container."""

import os
import signal

from cloneguard_interfaces.msg import ComponentEvent

from cloneguard.harness.rig import Rig


def test_a_container_that_died_in_a_trial_is_crashed_with_its_last_log_lines(container_factory):
    rig = Rig(container_factory, "threads")
    rig.proc.signal(signal.SIGSEGV)
    assert rig.proc.wait(timeout=20) is not None
    out = rig.not_survived("the container is gone")
    assert out.outcome == "crashed" and out.details["exit_code"] == -signal.SIGSEGV
    # What it said last stays in the report after its log file is gone: the
    # lines before the fault, and faulthandler's dump of its threads.
    assert "Loaded cloneguard::Heartbeat as /survivor" in out.details["log_tail"]
    fatal = out.details["fatal_error"]
    assert fatal.startswith("Fatal Python error: Segmentation fault") and "most recent call first" in fatal
    log = rig.proc.log_text()
    assert log.index(out.details["log_tail"]) + len(out.details["log_tail"]) <= log.index(fatal)


def test_a_long_fault_dump_keeps_the_faulting_threads_stack():
    from cloneguard.harness.rig import fatal_excerpt

    others = "".join(f'Thread 0x{i:x} (most recent call first):\n  File "x.py", line {i} in f\n\n' for i in range(400))
    current = (
        'Current thread 0xbeef (most recent call first):\n  Garbage-collecting\n  File "core.py", line 498 in _listen\n'
    )
    dump = "Fatal Python error: Segmentation fault\n\n" + others + current + "\nExtension modules: yaml\n"
    cut = fatal_excerpt(dump, 4000)
    assert len(cut) <= 4000
    assert cut.startswith("Fatal Python error: Segmentation fault\nCurrent thread 0xbeef")
    assert current in cut and "more characters of the dump left out" in cut
    assert fatal_excerpt("Fatal Python error: x\n", 4000) == "Fatal Python error: x\n"


def test_an_isolated_container_that_died_leaves_its_native_stack_and_the_deaths_before_it(container_factory):
    """Isolated mode: the container's own report of a fatal signal (its
    native stack, symbolized where the libraries allow) comes before
    faulthandler's dump, and the node deaths before it are kept with it."""
    import os

    from cloneguard_interfaces.msg import ComponentEvent

    rig = Rig(container_factory, "per-node")
    victim = rig.client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name="victim")
    pid = rig.loaded_pid(victim.unique_id)
    os.kill(pid, signal.SIGKILL)
    rig.client.wait_for_event(ComponentEvent.CRASHED, unique_id=victim.unique_id)
    rig.proc.signal(signal.SIGSEGV)
    assert rig.proc.wait(timeout=20) is not None
    out = rig.not_survived("the container is gone")
    native = out.details["native_stack"]
    assert native.startswith(f"cloneguard: container pid {rig.proc.pid} caught SIGSEGV"), native[:300]
    assert "cloneguard: native stack:" in native and "libc.so.6" in native
    assert " = " in native  # a frame named by addr2line
    assert out.details["fatal_error"].startswith("Fatal Python error: Segmentation fault")
    assert [d["node"] for d in out.details["deaths_before"]] == ["/victim"]
    assert "SIGKILL" in out.details["deaths_before"][0]["reason"]


def test_a_rig_replaces_its_container_after_its_bound_of_node_deaths(container_factory, monkeypatch):
    """Each dead per-node node leaves its participant's sockets in the
    container: a rig's container is replaced after DEATHS_PER_CONTAINER of
    them, survived or not, and not before."""
    from cloneguard.harness import rig as rig_module
    from cloneguard.harness.rig import Outcome, TrialOutcome

    monkeypatch.setattr(rig_module, "DEATHS_PER_CONTAINER", 2)
    rig = Rig(container_factory, "per-node")
    first = rig.proc.pid
    survived = Outcome(TrialOutcome.SURVIVED)
    for n in (1, 2):
        uid = rig.client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name=f"victim{n}").unique_id
        [pid] = [e.pid for e in rig.client.events.messages() if e.unique_id == uid and e.pid]
        os.kill(pid, signal.SIGKILL)
        rig.client.wait_for_event(ComponentEvent.CRASHED, unique_id=uid, timeout=10)
        assert rig.node_deaths() == n
        assert rig.settle(survived) is (n == 2)
    assert rig.proc.pid != first and rig.restarts == 1
    assert rig.node_deaths() == 0  # a fresh container, and the survivor beats in it
    rig.beats.wait_count(3, timeout=10)


def test_a_fault_node_that_outlives_its_judgement_and_dies_after_is_judged_once_dead(container_factory):
    """What OwnHeapOverflow relies on: judge_death says the node lived on
    (its one look, not a later /proc read); a node that dies after that
    can no longer be unloaded, and judging it again finds its death."""
    rig = Rig(container_factory, "per-node")
    node = rig.client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name="late")
    pid = rig.loaded_pid(node.unique_id)
    out = rig.judge_death(node.unique_id, pid, signal_expected=None, fault_ns=None, timeout=0.5)
    assert out.outcome == "failed" and out.fault_node_lived, out
    os.kill(pid, signal.SIGSEGV)
    rig.client.wait_for_event(ComponentEvent.CRASHED, unique_id=node.unique_id)
    assert not rig.client.unload(node.unique_id).success
    late = rig.judge_death(node.unique_id, pid, signal_expected=None, fault_ns=None)
    assert late.survived and not late.fault_node_lived and late.details["exit_signal"] == signal.SIGSEGV
