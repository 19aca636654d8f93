"""The launcher-side node-state tracker, on real containers."""

import os
import signal

import pytest
from cloneguard_interfaces.msg import ComponentEvent

from cloneguard.harness import procfs
from cloneguard.harness.tracker import NodeTracker, State

PKG = "cloneguard"
DROP = {"cloneguard.fault.drop_loaded_event": True}


@pytest.fixture
def tracker(client):
    t = NodeTracker(client, fallback_s=2.0)
    yield t
    t.close()


def test_load_then_unload(tracker):
    node = tracker.load(PKG, "cloneguard::Talker")
    assert tracker.wait_state(node, State.LOADED, timeout=10) == State.LOADED
    assert node.warnings == []
    tracker.unload(node)
    tracker.wait_state(node, State.UNLOADED, timeout=10)


def test_failed_load(tracker):
    node = tracker.load(PKG, "cloneguard::Nope")
    assert node.state == State.FAILED and "Failed to find class" in node.error


def test_lost_loaded_event_is_promoted_after_listnodes_confirms(tracker, client):
    node = tracker.load(PKG, "cloneguard::Talker", extra_arguments=DROP)
    assert node.state == State.LOADING and node.unique_id == 1
    tracker.wait_state(node, State.LOADED, timeout=10)
    assert "promoted to Loaded (ListNodes confirms it)" in node.warnings[0]
    # A LOADED event that turns up after the promotion changes nothing.
    late = ComponentEvent(event_type=ComponentEvent.LOADED, unique_id=node.unique_id)
    tracker._on_event(late)
    assert node.state == State.LOADED and len(node.warnings) == 1
    assert "late LOADED event ignored" in node.history[-1][2]


# No warm spare: it would be a second child.
@pytest.mark.parametrize("container_args", [["--isolated", "--no-warm-spare"]])
def test_a_node_gone_before_the_fallback_is_never_reported_loaded(tracker, client, container):
    node = tracker.load(PKG, "cloneguard::Heartbeat", extra_arguments=DROP)
    assert node.state == State.LOADING
    # No LOADED event, so no pid from it: the node's process is the
    # container's only child.
    (pid,) = procfs.children_of(container.pid)
    # Its CRASHED event is lost too: the tracker is not listening when it dies.
    client.events.remove_listener(tracker._on_event)
    os.kill(pid, signal.SIGKILL)
    client.wait_for_event(ComponentEvent.CRASHED, unique_id=node.unique_id)
    client.events.add_listener(tracker._on_event)
    assert tracker.wait_state(node, [State.LOADED, State.FAILED], timeout=10) == State.FAILED
    assert "not in ListNodes" in node.warnings[0]
