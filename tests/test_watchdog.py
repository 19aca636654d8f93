"""The watchdog ends a container whose executor stopped making progress."""
import pytest

from faults import PACKAGE as RIG


@pytest.mark.parametrize("container_args", [["--watchdog", "2"]])
def test_a_stalled_executor_is_reported_with_stacks_and_exit_1(client, container):
    # Thread mode, one executor: a callback that never returns stalls it all.
    client.load_ok(RIG, "faults::HangInCallback", parameters={"delay": 0.2})
    code = container.wait(timeout=20)
    assert code == 1, f"exit code {code}"
    log = container.log_text()
    # The dump was taken with the GIL held (the first stage), not by the
    # lock-free fallback.
    assert "cloneguard watchdog: no progress for 2 s" in log
    assert "Timeout (" not in log
    # The stuck thread's stack names the callback that hangs.
    assert "faults/components.py" in log and "in fire" in log


@pytest.mark.parametrize("container_args", [["--watchdog", "2"]])
def test_a_callback_that_keeps_the_gil_is_still_reported_and_ends_the_container(client, container):
    # No Python thread runs again, the watchdog's own included: the dump
    # comes from faulthandler's C thread, 2 s (the grace) later.
    client.load_ok(RIG, "faults::HangInCallback", parameters={"delay": 0.2, "mode": "gil"})
    code = container.wait(timeout=20)
    assert code == 1, f"exit code {code}"
    log = container.log_text()
    assert "Timeout (0:00:04)!" in log
    assert "cloneguard watchdog: no progress" not in log
    assert "faults/components.py" in log and "in fire" in log


@pytest.mark.parametrize("container_args", [["--watchdog", "2"]])
def test_an_idle_container_is_not_a_stalled_one(client, container):
    import time

    client.load_ok("cloneguard", "cloneguard::Talker")
    deadline = time.monotonic() + 5      # > twice the watchdog timeout
    while time.monotonic() < deadline:
        assert client.list()              # still answering
        time.sleep(0.5)
    assert container.alive()
