"""A container at rest: nothing of an earlier request still in flight.

An isolated container with the per-node profile keeps one child process made
ahead for its next load (its warm spare; the container's README), and makes
the next one after each load, off the request path. Every per-node process,
the spare too, holds a hidden placeholder node ``_cloneguard_process_<pid>``;
at rest (no node loaded) the one child with one is the spare. Its
children share the container's fd table, so counting the container's fds or
children right after a request can catch that spare half made. Wait for it.
"""
from __future__ import annotations

import time

from . import procfs

PROCESS_PLACEHOLDER = "_cloneguard_process_"


def with_placeholders(node, container_pid: int) -> list[int]:
    """The container's children whose placeholder is in ``node``'s graph."""
    names = {name for name, _ns in node.get_node_names_and_namespaces()}
    return [pid for pid in procfs.children_of(container_pid) if f"{PROCESS_PLACEHOLDER}{pid}" in names]


def wait_at_rest(node, container_pid: int, *, spare: bool, timeout: float = 10.0) -> list[int]:
    """Until the container's only child is its warm spare, placeholder
    announced (or it has none, with ``spare`` False); the children it has
    then, or at ``timeout``, for the caller to check."""
    deadline = time.monotonic() + timeout
    while True:
        children = procfs.children_of(container_pid)
        settled = (len(children) == 1 and with_placeholders(node, container_pid) == children) if spare else not children
        if settled or time.monotonic() >= deadline:
            return children
        time.sleep(0.01)
