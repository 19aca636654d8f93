"""What the benchmarks compare: the container modes measured side by side
(``MODES``, plus the process-per-node baseline) and the components they
load into them."""

from __future__ import annotations

PACKAGE = "cloneguard"
HEARTBEAT = "cloneguard::Heartbeat"
HEARTBEAT_PARAMS = {"period": 1.0}  # 1 Hz: an idle node, as the scale runs load them
LISTENER = "cloneguard::Listener"  # no timer: idle unless a message arrives


# Container modes: key -> (label, container arguments).
MODES = {
    "isolated-per-node": ("isolated, per-node profile", ["--isolated", "--profile", "per-node"]),
    "isolated-shared": ("isolated, shared profile", ["--isolated", "--profile", "shared"]),
    # A per-node isolation policy (--profile-for): most nodes shared, one in
    # ten (the benchmarks name nodes hb0, hb1, ...: hb0, hb10, hb20 ...)
    # in a process of its own.
    "isolated-mixed": (
        "isolated, shared, 1 node in 10 per-node",
        ["--isolated", "--profile", "shared", "--profile-for", "/hb*0=per-node"],
    ),
    # The default profile on the allocator that is not the default.
    "isolated-shared-glibc": (
        "isolated, shared profile, glibc malloc",
        ["--isolated", "--profile", "shared", "--allocator", "glibc"],
    ),
    "thread": ("thread mode (single-threaded executor)", []),
    "thread-mt": ("thread mode (multi-threaded executor)", ["--use_multi_threaded_executor"]),
    # What memory protection keys cost, side by side with the same allocator
    # without them (named with --modes only; --pkeys needs a CPU with PKU).
    "isolated-jemalloc": ("isolated, jemalloc, --no-pkeys", ["--isolated", "--jemalloc", "--no-pkeys"]),
    "isolated-pkeys": ("isolated, jemalloc, --pkeys", ["--isolated", "--jemalloc", "--pkeys"]),
}
#: the modes every benchmark that takes --modes can run by default
EVERYDAY_MODES = ["isolated-per-node", "isolated-shared", "thread", "thread-mt"]
PROCESS_PER_NODE = "process-per-node"
PROCESS_PER_NODE_LABEL = "process per node (fork+exec, bench.process_per_node)"


def isolated_default() -> str:
    """The mode of an isolated container started with no --profile. Read
    when asked: importing the container here would come before a benchmark
    that chooses which tree to import (accounting_cost) has chosen."""
    from cloneguard.container.isolated.profiles import DEFAULT

    return f"isolated-{DEFAULT}"


def label(mode: str) -> str:
    if mode == PROCESS_PER_NODE:
        return PROCESS_PER_NODE_LABEL
    return MODES[mode][0] + (" (the default)" if mode == isolated_default() else "")
