"""Being found: how long a fresh ROS process (a `ros2 component` command)
takes to see a container's node and its services.

    python -m cloneguard.bench.discovery                   # 20 probes per configuration
    python -m cloneguard.bench.discovery --probes 40 --nodes 0 4 16

For each mode (thread, isolated per-node, isolated shared) and count of
loaded cloneguard::Heartbeat nodes, a fresh container is started and loaded,
then ``--probes`` fresh processes (``bench._discovery_probe``, each a new DDS
participant, as every `ros2` command is) look for it one after another. A
probe reports when it first saw the container's node and its
``_container/list_nodes`` service; ros2cli's `ros2 component list` without a
daemon spins 0.5 s and then asks, so the share of probes that saw the
service within 0.5 s is the share of `ros2 component list` calls that find
the container.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from collections.abc import Sequence

from cloneguard.harness.process import REPO_ROOT, process_environment

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ms, stats
from .loads import timed_load
from .modes import MODES, label
from .results import Result, Table, summary_row
from .session import Session

NAME = "discovery"
TITLE = "Being found: a fresh process sees the container's node and services"
DEFAULT_MODES = ["thread", "isolated-per-node", "isolated-shared"]
ROS2CLI_SPIN_S = 0.5
PROBE_TIMEOUT_S = 5.0


def probe(running, nodes: Sequence[str] = (), timeout: float = PROBE_TIMEOUT_S) -> dict:
    """One fresh process's look: when it saw the container's node, its
    list_nodes service and every one of ``nodes`` (full names)."""
    env = process_environment(running.domain_id)
    command = [sys.executable, "-m", "cloneguard.bench._discovery_probe", running.proc.fqn, "--timeout", str(timeout)]
    done = subprocess.run(
        [*command, "--nodes", *nodes],
        cwd=REPO_ROOT,
        env=env,
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=timeout + 30,
    )
    if done.returncode != 0:
        raise RuntimeError(f"discovery probe exited with {done.returncode}: {done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def run(
    *,
    probes: int = 20,
    nodes: Sequence[int] = (0, 4),
    modes: Sequence[str] = DEFAULT_MODES,
    settle: float = 2.0,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
) -> Result:
    nodes, modes = list(nodes), list(modes)
    params = {"probes": probes, "nodes": nodes, "modes": modes, "settle": settle, "out": str(out)}
    session = Session(NAME, keep_logs=keep_logs)
    data: dict[str, list[dict]] = {}
    try:
        for count in nodes:
            for mode in modes:
                running = session.start(mode)
                try:
                    names = [f"/n{i}" for i in range(count)]
                    for name in names:
                        timed_load(running, node_name=name[1:])
                    time.sleep(settle)  # the container's own discovery traffic has settled
                    data[f"{mode}|{count}"] = [probe(running, names) for _ in range(probes)]
                finally:
                    session.stop(running)
    finally:
        problems = session.close()

    table = Table(
        f"A fresh participant finds the container (ms from its node's creation; {probes} probes, "
        "one after another, per row)",
        [
            "mode",
            "nodes loaded",
            "n",
            "node seen: median",
            "service seen: median",
            "service: p90",
            "service: max",
            f"seen within {ROS2CLI_SPIN_S:g} s (ros2 component list finds it)",
            "not seen in 5 s",
            "every loaded node seen: median",
            "every node: max",
            "every node within 1 s",
        ],
    )
    summary = []
    for count in nodes:
        for mode in modes:
            trials = data[f"{mode}|{count}"]
            node_st = stats([t["node_s"] * 1e3 for t in trials if t["node_s"] is not None])
            svc_st = stats([t["service_s"] * 1e3 for t in trials if t["service_s"] is not None])
            within = sum(t["service_s"] is not None and t["service_s"] <= ROS2CLI_SPIN_S for t in trials)
            missing = sum(t["service_s"] is None for t in trials)
            every = [t["all_nodes_s"] for t in trials]
            every_st = stats([e * 1e3 for e in every if e is not None])
            every_within = sum(e is not None and e <= 1.0 for e in every)
            table.add(
                label(mode),
                count,
                len(trials),
                fmt_ms(node_st["median"]),
                fmt_ms(svc_st["median"]),
                fmt_ms(svc_st["p90"]),
                fmt_ms(svc_st["max"]),
                f"{within}/{len(trials)}",
                missing,
                fmt_ms(every_st["median"]),
                fmt_ms(every_st["max"]),
                f"{every_within}/{len(trials)}",
            )
            summary.append(
                summary_row(
                    "discovery",
                    f"fresh process → list_nodes seen, {count} nodes",
                    label(mode),
                    svc_st,
                    goal="as thread mode",
                )
            )
    notes = [
        "Each probe is a new process with a new DDS participant (the ROS environment and Fast DDS profile "
        "the harness uses: UDP on loopback, participant discovery by multicast on lo, every participant "
        "re-announcing every 100 ms); it polls "
        "get_node_names_and_namespaces and get_service_names_and_types_by_node every 10 ms while spinning.",
        f"ros2cli's DirectNode spins {ROS2CLI_SPIN_S:g} s before `ros2 component list` asks the graph, so "
        "'seen within' is the share of such calls that list the container.",
        f"The container is loaded, then left {settle:g} s before the first probe.",
    ]
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, {"probes": probes, "nodes": nodes, "modes": modes}),
        params,
        [table],
        [],
        notes,
        summary,
        {"trials": data},
        problems,
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--probes", type=int, default=20)
    parser.add_argument("--nodes", type=int, nargs="+", default=[0, 4])
    parser.add_argument("--modes", nargs="+", choices=list(MODES), default=DEFAULT_MODES)
    parser.add_argument("--settle", type=float, default=2.0)
    args = parser.parse_args(argv)
    result = run(
        probes=args.probes,
        nodes=args.nodes,
        modes=args.modes,
        settle=args.settle,
        out=args.out,
        keep_logs=args.keep_logs,
    )
    return 1 if result.cleanup else 0


if __name__ == "__main__":
    sys.exit(main())
