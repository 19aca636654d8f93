"""SIGINT/SIGTERM: every node destroyed, exit 0, nothing left behind."""

import signal
import time

import pytest
from slow_load import SlowLoad

from cloneguard.harness import shm
from cloneguard.harness.process import SHM_PROFILE

PKG = "cloneguard"

MODES = [
    pytest.param([], id="single-threaded"),
    pytest.param(["--use_multi_threaded_executor"], id="multi-threaded"),
]


def _load_demo_set(cli):
    for plugin in ("Talker", "Listener", "EchoService", "Heartbeat"):
        cli.load_ok(PKG, f"cloneguard::{plugin}")


@pytest.mark.parametrize("container_args", MODES)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_signal_stops_the_container_cleanly(container, client, sig):
    _load_demo_set(client)
    container.signal(sig)
    code = container.wait(timeout=10)
    assert code == 0, f"exit code {code}\n{container.log_text()[-3000:]}"
    assert container.group_members() == []


def test_graceful_stop_with_shared_memory_leaves_no_segment(container_factory):
    before = shm.segments()
    proc = container_factory.start([], fastdds_profile=SHM_PROFILE)
    cli = container_factory.connect(proc)
    _load_demo_set(cli)
    # Only what this container maps: another session may make segments meanwhile.
    created = shm.belonging_to(shm.segments() - before, proc.record_shm())
    assert created, "with Fast DDS defaults the container should have made SHM segments"
    cli.close()
    proc.signal(signal.SIGTERM)
    assert proc.wait(timeout=10) == 0
    assert not (shm.segments() & created), "segments the container made were left behind"


@pytest.mark.parametrize("container_args", [["--isolated"]])
def test_a_load_waiting_for_its_node_is_answered_when_the_container_stops(container, client):
    # Stopping does not wait for a constructor (here 20 s): the LoadNode
    # still waiting is answered, failed, and the container exits 0 at once.
    slow = SlowLoad(client, seconds=20.0)
    t0 = time.monotonic()
    container.signal(signal.SIGTERM)
    code = container.wait(timeout=15)
    stopped_in = time.monotonic() - t0
    answer = slow.answer()
    assert code == 0, f"exit code {code}\n{container.log_text()[-3000:]}"
    assert stopped_in < 10, f"the stop took {stopped_in:.1f} s"
    assert not answer.success and answer.error_message == "the container is stopping", answer
    assert container.group_members() == []
