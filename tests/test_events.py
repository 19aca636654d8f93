"""ComponentEvent: one per load, failed load and unload, with its fields."""

import time

from cloneguard_interfaces.msg import ComponentEvent

PKG = "cloneguard"
TALKER = "cloneguard::Talker"


def test_loaded_and_unloaded_events_carry_the_node(client, container):
    before = time.time_ns()
    resp = client.load_ok(PKG, TALKER, node_name="t1", node_namespace="/ns")
    loaded = client.wait_for_event(ComponentEvent.LOADED, unique_id=resp.unique_id)
    assert loaded.full_node_name == "/ns/t1"
    assert (loaded.package_name, loaded.plugin_name) == (PKG, TALKER)
    assert loaded.pid == container.pid  # thread mode: the container's own pid
    assert before <= loaded.start_time <= time.time_ns()
    assert (loaded.exit_signal, loaded.exit_code, loaded.error_message) == (0, 0, "")
    assert client.unload(resp.unique_id).success
    unloaded = client.wait_for_event(ComponentEvent.UNLOADED, unique_id=resp.unique_id)
    assert unloaded.full_node_name == "/ns/t1"
    assert unloaded.start_time == loaded.start_time


def test_load_failed_event_says_why(client):
    client.load(PKG, "cloneguard::Nope")
    failed = client.wait_for_event(ComponentEvent.LOAD_FAILED)
    assert failed.unique_id == 0
    assert (failed.package_name, failed.plugin_name) == (PKG, "cloneguard::Nope")
    assert failed.error_message == "Failed to find class with the requested plugin name."


def test_events_are_latched_for_late_subscribers(container_factory, container):
    first = container_factory.connect(container)
    uid = first.load_ok(PKG, TALKER).unique_id
    first.wait_for_event(ComponentEvent.LOADED, unique_id=uid)
    # A client that joins afterwards still gets the LOADED event (transient_local).
    late = container_factory.connect(container)
    late.wait_for_event(ComponentEvent.LOADED, unique_id=uid)


def test_one_event_per_operation(client):
    ids = [client.load_ok(PKG, TALKER, node_name=f"n{i}").unique_id for i in range(3)]
    client.load(PKG, "cloneguard::Nope")
    client.unload(ids[1])
    client.wait_for_event(ComponentEvent.UNLOADED, unique_id=ids[1])
    kinds = [(e.event_type, e.unique_id) for e in client.events.messages()]
    assert kinds == [
        (ComponentEvent.LOADED, ids[0]),
        (ComponentEvent.LOADED, ids[1]),
        (ComponentEvent.LOADED, ids[2]),
        (ComponentEvent.LOAD_FAILED, 0),
        (ComponentEvent.UNLOADED, ids[1]),
    ]
