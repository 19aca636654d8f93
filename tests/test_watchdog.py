"""The watchdog ends a container whose executor stopped making progress."""

import signal
import time

import pytest

from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness.factory import log_tail


def _hang_until_the_watchdog_ends_it(client, container, mode: str) -> str:
    """Load a callback that never returns; the container must exit with 1
    and its log (returned) must show the stack of the callback that hangs."""
    client.load_ok(TESTRIG, "faults::HangInCallback", parameters={"delay": 0.2, "mode": mode})
    code = container.wait(timeout=20)
    assert code == 1, f"exit code {code}"
    log = container.log_text()
    assert "faults/components.py" in log and "in fire" in log
    # What a failing test shows of the log (the harness's teardown section)
    # holds every thread's stack, not only the last lines'.
    tail = log_tail(log)
    assert "in fire" in tail
    assert _threads_in(tail) == _threads_in(log) > 0
    return log


def _threads_in(text: str) -> int:
    return sum(line.startswith(("Thread 0x", "Current thread 0x")) for line in text.splitlines())


@pytest.mark.parametrize("container_args", [["--watchdog", "2"]])
def test_a_stalled_executor_is_reported_with_stacks_and_exit_1(client, container):
    # Thread mode, one executor: a callback that never returns stalls it all.
    log = _hang_until_the_watchdog_ends_it(client, container, "sleep")
    # The dump was taken with the GIL held (the first stage), not by the
    # lock-free fallback.
    assert "cloneguard watchdog: no progress for 2 s" in log
    assert "Timeout (" not in log


@pytest.mark.parametrize("container_args", [["--watchdog", "2"]])
def test_a_callback_that_keeps_the_gil_is_still_reported_and_ends_the_container(client, container):
    # No Python thread runs again, the watchdog's own included: the dump
    # comes from faulthandler's C thread, 2 s (the grace) later.
    log = _hang_until_the_watchdog_ends_it(client, container, "gil")
    assert "Timeout (0:00:04)!" in log
    assert "cloneguard watchdog: no progress" not in log


@pytest.mark.parametrize("container_args", [["--isolated", "--watchdog", "2"]])
def test_in_isolated_mode_the_clone_core_dumps_when_a_node_keeps_the_gil(client, container):
    # The node's process keeps the GIL: no thread of the container runs
    # Python again. The clone core's C thread (lastresort.c), not
    # faulthandler's, dumps 2 s after the watchdog's time.
    log = _hang_until_the_watchdog_ends_it(client, container, "gil")
    assert "cloneguard watchdog: no progress for 4 s and no Python thread could run since" in log
    assert "Timeout (" not in log


@pytest.mark.parametrize("container_args", [["--watchdog", "60", "--shutdown-timeout", "2"]])
def test_a_shutdown_that_does_not_end_is_reported_with_stacks_and_exit_1(client, container):
    # Thread mode stops its nodes' executor after their callbacks: one that
    # never returns would keep the stopping container alive, silent.
    client.load_ok(TESTRIG, "faults::HangInCallback", parameters={"delay": 0.0, "mode": "sleep"})
    deadline = time.monotonic() + 10
    while " hang-sleep firing at " not in container.log_text():
        assert time.monotonic() < deadline, container.log_text()
        time.sleep(0.05)
    container.signal(signal.SIGTERM)
    code = container.wait(timeout=20)
    assert code == 1, f"exit code {code}"
    log = container.log_text()
    assert "stopping (SIGTERM)" in log
    assert "cloneguard watchdog: still stopping for 2 s" in log
    assert "faults/components.py" in log and "in fire" in log


@pytest.mark.parametrize("container_args", [["--watchdog", "2"]])
def test_an_idle_container_is_not_a_stalled_one(client, container):
    import time

    client.load_ok("cloneguard", "cloneguard::Talker")
    deadline = time.monotonic() + 5  # > twice the watchdog timeout
    while time.monotonic() < deadline:
        assert client.list()  # still answering
        time.sleep(0.5)
    assert container.alive()


# --------------------------------------------------------------------------
# the node watchdog (isolated mode): a hung callback ends its node alone
# --------------------------------------------------------------------------
NODE_WATCHDOG = ["--isolated", "--node-watchdog", "1.5"]


@pytest.mark.parametrize("container_args", [NODE_WATCHDOG])
@pytest.mark.parametrize("mode", ["sleep", "spin"])
def test_a_node_whose_callback_hangs_is_aborted_alone_with_its_stacks(client, container, mode):
    from cloneguard_interfaces.msg import ComponentEvent

    beating = client.load_ok("cloneguard", "cloneguard::Heartbeat")
    hung = client.load_ok(TESTRIG, "faults::HangInCallback", parameters={"delay": 0.2, "mode": mode})
    crash = client.wait_for_event(ComponentEvent.CRASHED, unique_id=hung.unique_id, timeout=15)
    assert crash.exit_signal == 6, crash  # SIGABRT, sent by the container
    assert "longer than --node-watchdog 1.5 s (" in crash.error_message, crash.error_message
    assert "callback(s) had run before it)" in crash.error_message
    # Its crash report says where it hung (its stacks are written by the
    # container just after the CRASHED event); the rest goes on.
    deadline = time.monotonic() + 10
    while "native stack:" not in (log := container.log_text()) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert "caught SIGABRT" in log and "faults/components.py" in log and "in fire" in log
    assert [uid for uid, _ in client.list()] == [beating.unique_id]
    assert container.alive()


@pytest.mark.parametrize("container_args", [NODE_WATCHDOG])
def test_idle_and_busy_nodes_are_not_aborted(client, container):
    import time

    # A listener with nothing to hear runs no callback; a heartbeat runs
    # short ones all the time: neither is a hung callback.
    client.load_ok("cloneguard", "cloneguard::Listener")
    client.load_ok("cloneguard", "cloneguard::Heartbeat")
    time.sleep(4)  # > twice the limit
    assert len(client.list()) == 2
    assert "node watchdog" in container.log_text() and "aborting" not in container.log_text()


@pytest.mark.parametrize("container_args", [[]])
def test_a_container_that_crashes_itself_says_where(client, container):
    # Thread mode: the fault kills the container; its log shows the stack.
    client.load_ok(TESTRIG, "faults::SegfaultInCallback", parameters={"delay": 0.2})
    assert container.wait(timeout=20) == -11
    log = container.log_text()
    assert "Fatal Python error: Segmentation fault" in log
    assert "faults/components.py" in log and "in fire" in log
