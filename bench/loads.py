"""LoadNode and UnloadNode, timed: a node loaded into a running container
from the moment the request is sent, and the events that say so."""

from __future__ import annotations

import time
from dataclasses import dataclass

from cloneguard.harness.client import ContainerClient, Received

from .modes import HEARTBEAT, PACKAGE
from .session import Running


def event_received(cli: ContainerClient, event_type: int, unique_id: int, timeout: float) -> Received:
    """Wait for an event of ``unique_id``; return it with when the client got it."""
    msg = cli.events.wait_for(
        lambda ev: ev.event_type == event_type and ev.unique_id == unique_id,
        timeout,
        f"event {event_type} for unique_id {unique_id}",
    )
    for item in cli.events.items():
        if item.msg is msg:
            return item
    raise AssertionError("event seen but not recorded")


def stamp_ns(msg) -> int:
    return msg.stamp.sec * 1_000_000_000 + msg.stamp.nanosec


@dataclass
class LoadTrial:
    unique_id: int
    pid: int
    round_trip_ns: int  # LoadNode request sent -> response received
    loaded_ns: int  # request sent -> LOADED received by the client
    published_ns: int  # request sent (wall clock) -> LOADED's stamp (container's wall clock)


def timed_load(
    running: Running,
    *,
    node_name: str = "",
    plugin: str = HEARTBEAT,
    parameters: dict | None = None,
    timeout: float = 30.0,
) -> LoadTrial:
    """One LoadNode (a Heartbeat by default), timed from the moment the request is sent."""
    from cloneguard_interfaces.msg import ComponentEvent

    cli = running.client
    send_wall = time.time_ns()
    send = time.monotonic_ns()
    resp = cli.load(PACKAGE, plugin, node_name=node_name, parameters=parameters or {}, timeout=timeout)
    answered = time.monotonic_ns()
    if not resp.success:
        raise AssertionError(f"LoadNode failed in {running.label}: {resp.error_message}")
    item = event_received(cli, ComponentEvent.LOADED, resp.unique_id, timeout)
    return LoadTrial(resp.unique_id, item.msg.pid, answered - send, item.at_ns - send, stamp_ns(item.msg) - send_wall)


def timed_unload(running: Running, unique_id: int, timeout: float = 30.0) -> int:
    t0 = time.monotonic_ns()
    resp = running.client.unload(unique_id, timeout=timeout)
    t1 = time.monotonic_ns()
    if not resp.success:
        raise AssertionError(f"UnloadNode {unique_id} failed in {running.label}: {resp.error_message}")
    return t1 - t0
