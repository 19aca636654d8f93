"""Benchmarks of the container, run by hand from the repository root.

    python -m cloneguard.bench                    # all of them, small counts, + summary.md
    python -m cloneguard.bench.child_start        # time to start a node
    python -m cloneguard.bench.memory             # marginal memory per node
    python -m cloneguard.bench.crash_latency      # fault -> CRASHED latency
    python -m cloneguard.bench.load_latency       # LoadNode -> LOADED latency
    python -m cloneguard.bench.shutdown           # SIGTERM -> exit
    python -m cloneguard.bench.intra              # intra-process vs DDS latency and throughput
    python -m cloneguard.bench.leaks              # RSS, fds, threads per load cycle (long life)
    python -m cloneguard.bench.discovery          # how soon a fresh process (a ros2 command) finds a container
    python -m cloneguard.bench.random_kill        # random SIGKILLs of clone children (the core alone)
    python -m cloneguard.bench.alloc_guard        # the allocator guard's cost per malloc/free

Each writes ``reports/bench/<name>.md`` and ``<name>.json`` (``--out DIR``
elsewhere) and prints its table. ``bench.process_per_node`` is the
process-per-node baseline runner the benchmarks compare against.

This file stays empty of imports: the baseline runner is started as
``python -m cloneguard.bench.process_per_node`` and its start-up is measured.
"""
