"""What the benchmarks compare: the container modes measured side by side
(``MODES``, plus the process-per-node baseline) and the components they
load into them."""

from __future__ import annotations

PACKAGE = "cloneguard"
HEARTBEAT = "cloneguard::Heartbeat"
LISTENER = "cloneguard::Listener"  # no timer: idle unless a message arrives

# Container modes: key -> (label, container arguments).
MODES = {
    "isolated-per-node": ("isolated, per-node profile", ["--isolated", "--profile", "per-node"]),
    "isolated-shared": ("isolated, shared profile", ["--isolated", "--profile", "shared"]),
    "thread": ("thread mode (single-threaded executor)", []),
    "thread-mt": ("thread mode (multi-threaded executor)", ["--use_multi_threaded_executor"]),
}
PROCESS_PER_NODE = "process-per-node"
PROCESS_PER_NODE_LABEL = "process per node (fork+exec, bench.process_per_node)"


def label(mode: str) -> str:
    return PROCESS_PER_NODE_LABEL if mode == PROCESS_PER_NODE else MODES[mode][0]
