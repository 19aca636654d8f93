"""Each node's memory over time, as its container reports it on
``/diagnostics`` (container/diagnostics.py: once a second, or every
``diagnostic_updater.period`` s where the container's command line sets
it, a status a node
named ``<container>: <node>``, with ``memory_in_use_bytes`` and
``memory_limit_bytes`` where the allocator guard counts them, isolated
mode; thread mode reports none). The harness keeps every sample from the
start; a System asks for a node's (``System.memory``) and the report draws
them under a trial's timeline.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .client import ContainerClient

TOPIC = "/diagnostics"
MiB = 1 << 20


@dataclass(frozen=True)
class MemorySample:
    at_ns: int  # when the harness got it (time.monotonic_ns(), a recorder's clock)
    in_use: int  # bytes the node's process has in use, as the allocator guard counts them
    limit: int  # its budget in bytes; 0: none


class NodeMemory:
    """What the container named ``container_fqn`` said of its nodes'
    memory, heard on ``client``'s participant."""

    def __init__(self, client: ContainerClient, container_fqn: str):
        from diagnostic_msgs.msg import DiagnosticArray  # here: series_ms, for the report, needs no ROS

        self._container = container_fqn
        self._arrays = client.subscribe(DiagnosticArray, TOPIC, qos=100)

    def by_node(self, since_ns: int = 0, until_ns: int | None = None) -> dict[str, list[MemorySample]]:
        """Every node's samples heard from ``since_ns`` to ``until_ns``, in order."""
        out: dict[str, list[MemorySample]] = {}
        for item in self._arrays.items():
            if item.at_ns < since_ns or (until_ns is not None and item.at_ns > until_ns):
                continue
            for status in item.msg.status:
                if status.hardware_id != self._container:
                    continue  # another container of the same domain
                values = {kv.key: kv.value for kv in status.values}
                if "memory_in_use_bytes" not in values:
                    continue  # not counted (thread mode)
                node = status.name.split(": ", 1)[-1]
                sample = MemorySample(item.at_ns, int(values["memory_in_use_bytes"]), int(values["memory_limit_bytes"]))
                out.setdefault(node, []).append(sample)
        return out


def series_ms(samples: dict[str, list[MemorySample]], start_ns: int) -> dict[str, list[list[float]]]:
    """For a report: each node's [ms from ``start_ns``, MiB in use] pairs."""
    return {
        node: [[round((s.at_ns - start_ns) / 1e6, 1), round(s.in_use / MiB, 2)] for s in got]
        for node, got in samples.items()
    }
