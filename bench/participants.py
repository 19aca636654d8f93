"""What a DDS participant per node costs in one process, by node count:
the part of the per-node profile's cost that is Fast DDS's, apart from
the container.

    python -m cloneguard.bench.participants [--counts 1 12 24 48] [--settle 15] [--idle 10]

Each count runs in a fresh worker process (no container, no clone child,
no executor), on a ROS domain of its own under the harness's no-SHM Fast
DDS profile, in two shapes side by side:

* one participant: N plain rclpy nodes on one Context (the shared
  profile's shape: every node on the container's participant);
* a participant per node: the first Context's participant announces at
  the profile's period (as the container's own), then N Contexts with a
  node each, announcing every 3 s (as the container's node processes do:
  --node-announcement, isolated/dds_defaults.py).

Measured: the time to make all N (Context and node), the process's PSS
after ``--settle`` s (smaps_rollup), its CPU over ``--idle`` s of nothing
but DDS (getrusage: every thread), and its threads. The difference between
the shapes, per node, is what each participant costs; how it grows with N
is discovery's share (every participant learns every other one and each of
its endpoints).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from cloneguard.container.cli import NODE_ANNOUNCEMENT_S
from cloneguard.harness import domains
from cloneguard.harness.process import NO_SHM_PROFILE, REPO_ROOT, process_environment

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .results import Result, Table

NAME = "participants"
TITLE = "A DDS participant per node: what it costs in one process, by node count"
SHAPES = {"one": "one participant, N nodes", "per-node": "a participant per node"}
# The nodes' endpoints, which every other participant keeps a proxy of:
# rclpy's defaults (6 parameter services, /rosout, /parameter_events), or
# without the parameter services and /rosout.
NODE_OPTIONS: dict[str, dict] = {
    "all": {},
    "minimal": {"start_parameter_services": False, "enable_rosout": False},
}


def _pss_kib() -> int:
    with open("/proc/self/smaps_rollup") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("Pss:"))


def _cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def _worker(shape: str, n: int, settle: float, idle: float, arenas: str, endpoints: str) -> dict:
    """One count and shape, in this process (a fresh one per call)."""
    if arenas == "per-task":
        from cloneguard.container import allocator

        allocator.glibc_arena_per_task()  # before a second thread, as the container does
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    from cloneguard.container.isolated.dds_defaults import announce_nodes_every

    t0 = time.monotonic()
    first = Context()
    rclpy.init(context=first)
    contexts, nodes = [first], [Node("container", context=first)]
    if shape == "per-node":
        announce_nodes_every(NODE_ANNOUNCEMENT_S)
    for i in range(n):
        if shape == "per-node":
            ctx = Context()
            rclpy.init(context=ctx)
            contexts.append(ctx)
        nodes.append(Node(f"n{i}", context=contexts[-1], **NODE_OPTIONS[endpoints]))
    made_s = time.monotonic() - t0
    time.sleep(settle)
    pss = _pss_kib()
    cpu0, w0 = _cpu_s(), time.monotonic()
    time.sleep(idle)
    cpu = (_cpu_s() - cpu0) / (time.monotonic() - w0)
    threads = len(os.listdir("/proc/self/task"))
    for node in nodes:
        node.destroy_node()
    for ctx in contexts:
        rclpy.shutdown(context=ctx)
    return {"made_s": made_s, "pss_kib": pss, "cpu_share": cpu, "threads": threads}


def measure(counts: list[int], profile: Path, **worker) -> dict:
    """Figures by count and shape, each from a fresh worker process
    (``worker``: _worker's settle, idle, arenas and endpoints)."""
    data: dict[int, dict[str, dict]] = {}
    for n in counts:
        for shape in SHAPES:  # the two shapes of one count in turn
            lease = domains.lease()
            try:
                proc = subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        f"cloneguard.bench.{NAME}",
                        "--worker",
                        json.dumps(worker | {"shape": shape, "n": n}),
                    ],
                    capture_output=True,
                    text=True,
                    env=process_environment(lease.domain_id, fastdds_profile=profile),
                    cwd=REPO_ROOT,
                    timeout=600 + worker["settle"] + worker["idle"],
                )
            finally:
                lease.release()
            if proc.returncode != 0:
                raise RuntimeError(f"worker ({shape}, {n}) failed:\n{proc.stderr[-3000:]}")
            data.setdefault(n, {})[shape] = json.loads(proc.stdout.strip().splitlines()[-1])
    return data


def run(
    *,
    counts: list[int] | tuple[int, ...] = (1, 12, 24, 48),
    settle: float = 15.0,
    idle: float = 10.0,
    arenas: str = "per-task",
    fastdds_profile: Path = NO_SHM_PROFILE,
    endpoints: str = "all",
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
) -> Result:
    del keep_logs  # no container: nothing logs
    args = {"counts": list(counts), "settle": settle, "idle": idle, "arenas": arenas, "endpoints": endpoints}
    if Path(fastdds_profile) != NO_SHM_PROFILE:
        args["fastdds_profile"] = str(fastdds_profile)
    data = measure(list(counts), Path(fastdds_profile), settle=settle, idle=idle, arenas=arenas, endpoints=endpoints)
    table = Table(
        "By node count and shape (one worker process each)",
        ["nodes", "shape", "make all (s)", "PSS (MiB)", "idle CPU (% of a core)", "threads"],
    )
    per = Table(
        "A participant per node, less one participant: per node",
        ["nodes", "make (ms per node)", "PSS (MiB per node)", "idle CPU (% of a core per node)", "threads per node"],
    )
    for n, shapes in data.items():
        for shape, d in shapes.items():
            table.add(
                n,
                SHAPES[shape],
                f"{d['made_s']:.2f}",
                f"{d['pss_kib'] / 1024:.0f}",
                f"{100 * d['cpu_share']:.1f}",
                d["threads"],
            )
        one, each = shapes["one"], shapes["per-node"]
        per.add(
            n,
            f"{1000 * (each['made_s'] - one['made_s']) / n:.1f}",
            f"{(each['pss_kib'] - one['pss_kib']) / 1024 / n:.2f}",
            f"{100 * (each['cpu_share'] - one['cpu_share']) / n:.2f}",
            f"{(each['threads'] - one['threads']) / n:.1f}",
        )
    notes = [
        "Plain rclpy nodes, no timer, no executor: what is measured is rclpy's Context and Fast DDS, not the "
        "container.",
        f"A participant per node: the first Context's participant at the profile's announcement period (100 ms), "
        f"the node's at {NODE_ANNOUNCEMENT_S:g} s, as in a per-node container.",
        "Each node's endpoints: "
        + (
            "rclpy's defaults (6 parameter services, /rosout, /parameter_events)."
            if endpoints == "all"
            else "no parameter services and no /rosout (start_parameter_services=False, enable_rosout=False)."
        ),
        "glibc malloc, "
        + (
            "an arena per thread (mallopt M_ARENA_MAX, as the isolated container without --jemalloc)."
            if arenas == "per-task"
            else "glibc's own arenas (8 per core)."
        ),
    ]
    result = Result(
        NAME, TITLE, command_line(NAME, args), args | {"out": str(out)}, [table, per], [], notes, [], data, []
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--counts", type=int, nargs="+", default=[1, 12, 24, 48])
    parser.add_argument("--settle", type=float, default=15.0, help="s after the last node, before PSS")
    parser.add_argument("--idle", type=float, default=10.0, help="s of idle CPU measured")
    parser.add_argument(
        "--arenas",
        choices=("per-task", "glibc"),
        default="per-task",
        help="glibc malloc with an arena per thread, as the isolated container has it, or glibc's own few "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--fastdds-profile",
        type=Path,
        default=NO_SHM_PROFILE,
        help="the Fast DDS XML profile the workers run under (default: the harness's no-SHM one)",
    )
    parser.add_argument(
        "--endpoints",
        choices=list(NODE_OPTIONS),
        default="all",
        help="the N nodes with every endpoint an rclpy node has, or 'minimal': no parameter services, "
        "no /rosout (default: %(default)s)",
    )
    parser.add_argument("--worker", metavar="JSON", help=argparse.SUPPRESS)
    opts = parser.parse_args(argv)
    if opts.worker:
        print(json.dumps(_worker(**json.loads(opts.worker))))
        return 0
    run(
        counts=opts.counts,
        settle=opts.settle,
        idle=opts.idle,
        arenas=opts.arenas,
        fastdds_profile=opts.fastdds_profile,
        endpoints=opts.endpoints,
        out=opts.out,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
