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
    assert "Timeout (0:00:02)!" in log
    # The stuck thread's stack names the callback that hangs.
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
