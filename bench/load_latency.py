"""LoadNode -> LOADED latency, per container mode.

    python -m cloneguard.bench.load_latency                 # n=30 per mode
    python -m cloneguard.bench.load_latency --n 100 --modes isolated-per-node thread

One container per mode, all started first; then ``n`` rounds, each loading
one cloneguard::Heartbeat into every container in turn (interleaved, so the
host's noise falls on all modes alike) and unloading it again, so every load
is into a container holding no other node. The first load of each container
(it imports the component's module) is reported apart as "cold".

Measured at the client (harness.client.ContainerClient, CLOCK_MONOTONIC):
the request sent -> the LOADED event received, and -> the LoadNode response
received (round trip); and, on the wall clock, request sent -> the LOADED
event's stamp (when the container published it). Goals: median ≤ 20 ms;
the per-node profile's median within 1.3× of thread mode's.
"""

from __future__ import annotations

import sys
from typing import Any

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ms, fmt_ratio, ms, stats
from .goals import goal_at_most, goal_ratio_at_most
from .loads import timed_load, timed_unload
from .modes import EVERYDAY_MODES, HEARTBEAT, MODES, PACKAGE
from .results import Result, Table, summary_row
from .session import Session

NAME = "load_latency"
TITLE = "LoadNode → LOADED latency"
GOAL_MS = 20.0
PER_NODE_VS_THREAD = 1.3  # per-node median ÷ thread mode's, at most
DEFAULT_MODES = EVERYDAY_MODES


def measure(session: Session, modes: list[str], n: int) -> dict:
    """{mode: {"cold": LoadTrial fields, "loaded": [ns], "round_trip": [ns], ...}}"""
    running = {mode: session.start(mode) for mode in modes}
    data: dict[str, dict[str, Any]] = {
        mode: {"cold": None, "loaded": [], "round_trip": [], "published": [], "unload": []} for mode in modes
    }
    for i in range(n + 1):
        for mode in modes:
            trial = timed_load(running[mode], node_name=f"hb{i}")
            unload = timed_unload(running[mode], trial.unique_id)
            d = data[mode]
            if i == 0:
                d["cold"] = {
                    "loaded": trial.loaded_ns,
                    "round_trip": trial.round_trip_ns,
                    "published": trial.published_ns,
                    "unload": unload,
                }
                continue
            d["loaded"].append(trial.loaded_ns)
            d["round_trip"].append(trial.round_trip_ns)
            d["published"].append(trial.published_ns)
            d["unload"].append(unload)
    for r in running.values():
        session.stop(r)
    return data


def registry_lookup(n: int) -> list[int]:
    """What every LoadNode spends finding its class: container.registry.find
    (a scan of the installed distributions' entry points) + load_class, timed
    here in the benchmark process (same venv, module already imported)."""
    import time

    from cloneguard.container import registry

    out = []
    for _ in range(n + 1):
        t0 = time.monotonic_ns()
        registry.find(PACKAGE, HEARTBEAT).load_class()
        out.append(time.monotonic_ns() - t0)
    return out[1:]


def run(
    *, n: int = 30, modes: list[str] = DEFAULT_MODES, out=DEFAULT_OUT, keep_logs: bool = False, quiet: bool = False
) -> Result:
    params = {"n": n, "modes": list(modes), "out": str(out)}
    session = Session(NAME, keep_logs=keep_logs)
    try:
        data = measure(session, list(modes), n)
    finally:
        problems = session.close()
    lookup = registry_lookup(max(n, 5))

    table = Table(
        f"Latency per mode (ms; n={n} warm loads each, the cold first load apart)",
        [
            "mode",
            "n",
            "→ LOADED at client: median",
            "→ LOADED: p90",
            "LoadNode round trip: median",
            "round trip: p90",
            "→ LOADED published (container clock): median",
            "cold first load → LOADED",
            "UnloadNode round trip: median",
            "LOADED median vs goal 20 ms",
        ],
    )
    goals, summary = [], []
    for mode in modes:
        d = data[mode]
        loaded, rt, pub, unl = (stats(ms(d[k])) for k in ("loaded", "round_trip", "published", "unload"))
        goal = goal_at_most(
            "median ≤ 20 ms", f"{MODES[mode][0]}: request → LOADED at client", loaded["median"], GOAL_MS, "ms"
        )
        goals.append(goal)
        table.add(
            MODES[mode][0],
            loaded["n"],
            fmt_ms(loaded["median"]),
            fmt_ms(loaded["p90"]),
            fmt_ms(rt["median"]),
            fmt_ms(rt["p90"]),
            fmt_ms(pub["median"]),
            fmt_ms(d["cold"]["loaded"] / 1e6),
            fmt_ms(unl["median"]),
            goal.verdict,
        )
        summary.append(
            summary_row(
                "load latency",
                "LoadNode sent → LOADED at client",
                MODES[mode][0],
                loaded,
                goal="median ≤ 20 ms",
                verdict=goal.verdict,
            )
        )
    if "isolated-per-node" in modes and "thread" in modes:
        per_node, thread = (stats(ms(data[m]["loaded"]))["median"] for m in ("isolated-per-node", "thread"))
        goal = goal_ratio_at_most(
            f"≤ {fmt_ratio(PER_NODE_VS_THREAD)} thread mode",
            "request → LOADED at client: per-node median ÷ thread mode's",
            per_node / thread,
            PER_NODE_VS_THREAD,
        )
        goals.append(goal)
        summary.append(
            summary_row(
                "load latency",
                "LoadNode → LOADED: per-node ÷ thread mode",
                f"{MODES['isolated-per-node'][0]} vs {MODES['thread'][0]}",
                None,
                median=f"{fmt_ms(per_node)} vs {fmt_ms(thread)} ms ({goal.measured})",
                goal=goal.goal,
                verdict=goal.verdict,
            )
        )
    lk = stats(ms(lookup))
    notes = [
        f"Part of every LoadNode, in every mode: finding the class (container.registry.find scans the "
        f"entry points of every installed distribution, then load_class) took a median "
        f"{fmt_ms(lk['median'])} ms (p90 {fmt_ms(lk['p90'])} ms, n={lk['n']}), timed in the benchmark "
        f"process on the same venv.",
        "Each load is of cloneguard::Heartbeat (unique node names), into a container holding no other "
        "node: every load is followed by its UnloadNode before the next mode's turn.",
        "Times are CLOCK_MONOTONIC in the benchmark process: stamped before ContainerClient.load() "
        "sends the request, when the response future completes, and when the client's subscription "
        "callback records the LOADED event. 'Published' compares the benchmark's wall clock at "
        "sending with the event's stamp (set by the container just before it publishes).",
        "The container publishes LOADED before it answers the request, so LOADED can arrive before the response.",
        "UnloadNode in isolated mode returns once the child has ended and been reaped: the host sets its "
        "stop flag and triggers a guard condition of its executor, and the child leaves its spin loop, "
        "destroys its node (per-node: and its Context and participant) and exits.",
        "Isolated per-node: the node is built in the warm spare, a clone child whose rclpy Context and "
        "DDS participant were made ahead (container/isolated/spare.py), and the next spare is made "
        "right after the load, while its UnloadNode runs; isolated shared: the node is built on the "
        "container's participant and only spun in the child; thread mode: built on the container's "
        "participant and added to its executor.",
        "Containers launched as the harness does (ContainerProcess: setpriv --pdeathsig, no-SHM Fast "
        "DDS profile), each on its own ROS domain (harness.domains.lease()).",
    ]
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, {"n": n, "modes": list(modes)}),
        params,
        [table],
        goals,
        notes,
        summary,
        {"ns": data, "registry_lookup_ns": lookup},
        problems,
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--n", type=int, default=30, help="warm loads per mode (default: %(default)s)")
    parser.add_argument("--modes", nargs="+", choices=list(MODES), default=DEFAULT_MODES)
    opts = parser.parse_args(argv)
    result = run(n=opts.n, modes=opts.modes, out=opts.out, keep_logs=opts.keep_logs)
    return 1 if result.cleanup else 0


if __name__ == "__main__":
    sys.exit(main())
