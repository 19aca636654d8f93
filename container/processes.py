"""Which node process is which, for naming what a dead one left behind (a
Python lock, a native mutex): pid -> (unique_id, full node name).

The isolated host says so as each node's process starts; entries stay (a
dead process is named after its death, and pids come round only after
pid_max others).
"""

from __future__ import annotations

import os

# Imported by the container before any node process exists (node processes
# share the module, and getpid() in one is its own pid).
_CONTAINER_PID = os.getpid()
_nodes: dict[int, tuple[int, str]] = {}


def node_is(pid: int, unique_id: int, full_node_name: str) -> None:
    """Process ``pid`` runs load ``unique_id`` (name "" until it is built)."""
    _nodes[pid] = (unique_id, full_node_name)


def node_of(pid: int) -> tuple[int, str]:
    """(unique_id, full node name) of process ``pid``; (0, "") if unknown."""
    return _nodes.get(pid, (0, ""))


def who(pid: int) -> str:
    """ "/ns/node (pid 7)", "the container (pid 5)" or "pid 7"."""
    if pid == _CONTAINER_PID:
        return f"the container (pid {pid})"
    name = _nodes.get(pid, (0, ""))[1]
    return f"{name} (pid {pid})" if name else f"pid {pid}"
