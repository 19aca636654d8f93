"""A container at rest: nothing of an earlier request still in flight.

An isolated container with the per-node profile keeps one child process made
ahead for its next load (its warm spare: docs/architecture.md), which
holds a hidden placeholder node ``_cloneguard_spare_<pid>`` until a load
takes it, and makes the next one after each load, off the request path. Its
children share the container's fd table, so counting the container's fds or
children right after a request can catch that spare half made. Wait for it.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from . import procfs

if TYPE_CHECKING:
    from rclpy.node import Node

SPARE_PLACEHOLDER = "_cloneguard_spare_"


def warm_spares(node: Node, container_pid: int) -> list[int]:
    """The container's children whose placeholder is in ``node``'s graph."""
    names = {name for name, _ns in node.get_node_names_and_namespaces()}
    return [pid for pid in procfs.children_of(container_pid) if f"{SPARE_PLACEHOLDER}{pid}" in names]


def wait_at_rest(node: Node, container_pid: int, *, spare: bool, timeout: float = 10.0) -> list[int]:
    """Until the container's only child is its warm spare, placeholder
    announced (or it has none, with ``spare`` False); the children it has
    then, or at ``timeout``, for the caller to check."""
    deadline = time.monotonic() + timeout
    while True:
        children = procfs.children_of(container_pid)
        settled = (len(children) == 1 and warm_spares(node, container_pid) == children) if spare else not children
        if settled or time.monotonic() >= deadline:
            return children
        time.sleep(0.01)


def wait_for_spare(node: Node, container_pid: int, timeout: float = 10.0) -> bool:
    """Until the container has a warm spare whose placeholder is announced
    (its participant, and so its shared-memory ports, made); False at
    ``timeout`` (a container that keeps none)."""
    deadline = time.monotonic() + timeout
    while not warm_spares(node, container_pid):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True
