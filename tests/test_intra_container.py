"""Intra-process messaging on real containers: every mode, and the DDS edge.

The demo talker and listener use container.intra; the listener publishes,
per message, how many it has received (``~/received``) and how many of those
were handed over by reference (``~/by_reference``).
"""

import os
import signal
import time

import pytest
from cloneguard_interfaces.msg import ComponentEvent
from std_msgs.msg import String, UInt64

PKG = "cloneguard"
INTRA = {"use_intra_process_comms": True}
MODES = [
    pytest.param([], id="single-threaded"),
    pytest.param(["--use_multi_threaded_executor"], id="multi-threaded"),
    pytest.param(["--isolated", "--profile", "per-node"], id="per-node"),
    pytest.param(["--isolated", "--profile", "shared"], id="shared"),
]
PER_NODE = [MODES[2]]
N = 40


def _values(rec) -> list[int]:
    return [m.data for m in rec.messages()]


def _wait_discovered(client, topic: str) -> None:
    """Until this client knows the publisher of ``topic`` (a condition, bounded)."""
    deadline = time.monotonic() + 15
    while client.node.count_publishers(topic) == 0:
        assert time.monotonic() < deadline, f"no publisher of {topic} discovered"
        time.sleep(0.01)


def _load_listener(client, topic, intra=True, name="lis"):
    client.load_ok(
        PKG, "cloneguard::Listener", node_name=name, parameters={"topic": topic}, extra_arguments=INTRA if intra else {}
    )
    counts = client.subscribe(UInt64, f"/{name}/received"), client.subscribe(UInt64, f"/{name}/by_reference")
    for topic in (f"/{name}/received", f"/{name}/by_reference"):
        _wait_discovered(client, topic)
    return counts


def _load_talker(client, topic, intra=True, limit=N):
    return client.load_ok(
        PKG,
        "cloneguard::Talker",
        node_name="tlk",
        parameters={"topic": topic, "period": 0.01, "limit": limit},
        extra_arguments=INTRA if intra else {},
    )


@pytest.mark.parametrize("container_args", MODES)
def test_every_message_is_handed_over_by_reference_exactly_once(client):
    received, by_ref = _load_listener(client, "/intra_a")
    _load_talker(client, "/intra_a")
    by_ref.wait_for(lambda m: m.data == N, timeout=15)
    received.wait_for(lambda m: m.data >= N, timeout=5)
    # Both counts go out from the same callback: had any message also come
    # over DDS, the received count would be ahead of N by now.
    assert max(_values(received)) == N


@pytest.mark.parametrize("container_args", PER_NODE)
def test_an_outside_subscriber_gets_it_over_dds_and_inside_nothing_is_doubled(client):
    outside = client.subscribe(String, "/intra_b")
    received, by_ref = _load_listener(client, "/intra_b")
    _load_talker(client, "/intra_b", limit=0)
    outside.wait_count(20, timeout=15)  # the talker saw a subscriber outside: DDS too
    # 20 more by reference while DDS carries them too: the received count
    # (same callback) must not have run ahead of the by-reference one.
    target = _values(by_ref)[-1] + 20
    by_ref.wait_for(lambda m: m.data >= target, timeout=10)
    received.wait_for(lambda m: m.data >= target, timeout=5)
    assert max(_values(received)) <= max(_values(by_ref)) + 1
    numbers = [int(m.data.split()[-1]) for m in outside.messages()]
    assert numbers == sorted(set(numbers)), "the outside subscriber got duplicates or disorder"


@pytest.mark.parametrize("container_args", PER_NODE)
def test_an_outside_publisher_reaches_an_intra_process_subscription(client):
    received, by_ref = _load_listener(client, "/intra_c")
    pub = client.node.create_publisher(String, "/intra_c", 10)
    deadline = time.monotonic() + 15
    while pub.get_subscription_count() == 0:  # discovery: a condition, bounded
        assert time.monotonic() < deadline, "the listener's DDS reader never matched"
        time.sleep(0.01)
    _wait_discovered(client, "/lis/received")
    for i in range(5):
        pub.publish(String(data=f"outside {i}"))
    received.wait_for(lambda m: m.data == 5, timeout=10)
    assert set(_values(by_ref)) == {0}


@pytest.mark.parametrize("container_args", PER_NODE)
def test_without_use_intra_process_comms_messages_go_over_dds(client):
    received, by_ref = _load_listener(client, "/intra_d", intra=False)
    _load_talker(client, "/intra_d", intra=False, limit=0)
    received.wait_count(10, timeout=15)
    assert set(_values(by_ref)) == {0}


@pytest.mark.parametrize("container_args", PER_NODE)
def test_a_dead_subscriber_is_forgotten_and_the_publisher_goes_on(client):
    received, _ = _load_listener(client, "/intra_e")
    lis_id = next(uid for uid, name in client.list() if name == "/lis")
    _load_talker(client, "/intra_e", limit=0)
    received.wait_count(5, timeout=10)
    pid = client.wait_for_event(ComponentEvent.LOADED, unique_id=lis_id).pid
    os.kill(pid, signal.SIGKILL)
    client.wait_for_event(ComponentEvent.CRASHED, unique_id=lis_id)
    _, by_ref2 = _load_listener(client, "/intra_e", name="lis2")
    by_ref2.wait_for(lambda m: m.data >= 5, timeout=10)


@pytest.mark.parametrize("container_args", PER_NODE)
def test_a_dead_publisher_leaves_the_subscriber_receiving_from_the_next(client):
    _, by_ref = _load_listener(client, "/intra_f")
    tlk_id = _load_talker(client, "/intra_f", limit=0).unique_id
    by_ref.wait_for(lambda m: m.data >= 5, timeout=10)
    pid = client.wait_for_event(ComponentEvent.LOADED, unique_id=tlk_id).pid
    os.kill(pid, signal.SIGKILL)
    client.wait_for_event(ComponentEvent.CRASHED, unique_id=tlk_id)
    seen = _values(by_ref)[-1]
    client.load_ok(
        PKG,
        "cloneguard::Talker",
        node_name="tlk2",
        parameters={"topic": "/intra_f", "period": 0.01},
        extra_arguments=INTRA,
    )
    by_ref.wait_for(lambda m: m.data >= seen + 5, timeout=10)
