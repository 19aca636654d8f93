"""Scale: how the cost of each mode grows with the number of nodes.

    python -m cloneguard.bench.scale                          # 12, 24, 48 nodes, every mode
    python -m cloneguard.bench.scale --counts 12 24 48 96 --idle 10
    python -m cloneguard.bench.scale --discovery-server     # every mode under a discovery server

For each node count and mode (thread mode, isolated shared, isolated
shared with one node in ten per-node (``--profile-for``), isolated
per-node, and process-per-node: one fork+exec'd runner a node), one after
the other on a fresh container (or fresh runners): ``count``
cloneguard::Heartbeat nodes at 1 Hz (``period`` 1.0) are loaded one after
another (**load all**: first request sent to the last LOADED; runners:
first spawn to the last ready line); after ``--settle`` s (15: discovery
among the participants outlasts the loads), **idle CPU** is
the CPU time every process involved used over ``--idle`` s (utime + stime
of the container and every process of its group, or of every runner), as
a percentage of one core; then **PSS** (memory.footprint: each address
space counted once); then **SIGTERM → exit**: the container process
(bench.shutdown.sigterm_to_exit), or every runner at once until the last
has exited.

The picture (``scale.svg``, beside ``scale.md``) draws each measure
against the node count, a line a mode. Goals, judged at 48 nodes (or the
largest count measured): per-node load-all ≤ 2× thread mode's; per-node
idle CPU and PSS ≤ 1.5× the shared profile's; per-node SIGTERM → exit
≤ 2 s; thread mode idle CPU ≤ 30% of a core. At 96 (or the largest count),
the default profile's: load all ≤ 3 s, idle CPU ≤ 15% of a core, PSS ≤
270 MiB, SIGTERM → exit ≤ 2 s.

With ``--discovery-server`` every participant, the benchmark's own
included, finds the others through a Fast DDS discovery server of the
benchmark's own (bench.discovery_server, ``ROS_DISCOVERY_SERVER``)
instead of by multicast, and the results are written as
``scale-discovery-server``; the server's own PSS and CPU are in the notes.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence

from cloneguard.harness import procfs

from . import discovery_server as ds
from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ratio
from .goals import Goal, goal_at_most, goal_ratio_at_most
from .loads import timed_load
from .memory import footprint
from .modes import HEARTBEAT_PARAMS, PROCESS_PER_NODE, isolated_default, label
from .results import Result, Table, summary_row
from .scale_chart import scale_svg
from .session import Session
from .shutdown import sigterm_to_exit

NAME = "scale"
TITLE = "Scale: N nodes at 1 Hz, per mode"
DEFAULT_MODES = ["thread", "isolated-shared", "isolated-mixed", "isolated-per-node", PROCESS_PER_NODE]
GOAL_NODES = 48
DEFAULT_GOAL_NODES = 96
#: From the last load to the idle window: discovery among the participants
#: goes on after the loads (measured, per-node at 48 nodes with 3 s node
#: announcements: 139% of a core 2 s after the last load, 12% after 20 s).
SETTLE_S = 15.0
CLK_TCK = os.sysconf("SC_CLK_TCK")
EXIT_TIMEOUT_S = 60.0


def cpu_seconds(pids: list[int]) -> float:
    """utime + stime of these processes (each a whole thread group), in s."""
    stats = (procfs.stat(pid) for pid in pids)
    return sum(st.cpu_ticks for st in stats if st is not None) / CLK_TCK


def dds_thread_ticks(pids: list[int]) -> dict[tuple[int, int], int]:
    """(pid, tid) -> CPU ticks of each Fast DDS thread (Fast DDS names its
    threads dds.*: receive, event, asynchronous writer...) of these processes."""
    return {
        (pid, tid): ticks
        for pid in pids
        for tid, (name, ticks) in procfs.threads(pid).items()
        if name.startswith("dds.")
    }


def idle_cpu_percent(pids_fn, seconds: float) -> tuple[float, float]:
    """CPU the processes used over ``seconds``, as % of one core: all of
    it, and their Fast DDS threads' part (of the threads there throughout,
    read inside the window the whole is read over)."""
    pids = pids_fn()
    t0, c0, d0 = time.monotonic(), cpu_seconds(pids), dds_thread_ticks(pids)
    time.sleep(seconds)
    d1, c1, t1 = dds_thread_ticks(pids), cpu_seconds(pids), time.monotonic()
    dds = sum(d1[k] - d0[k] for k in d0.keys() & d1.keys()) / CLK_TCK
    return 100.0 * (c1 - c0) / (t1 - t0), 100.0 * dds / (t1 - t0)


def measure_container(session: Session, mode: str, count: int, settle: float, idle: float) -> dict:
    running = session.start(mode)
    try:
        t0 = time.monotonic_ns()
        for i in range(count):
            timed_load(running, node_name=f"hb{i}", parameters=HEARTBEAT_PARAMS, timeout=120.0)
        load_all = time.monotonic_ns() - t0

        def pids():
            return [running.proc.pid] + [p for p in running.proc.group_members() if p != running.proc.pid]

        time.sleep(settle)
        cpu = idle_cpu_percent(pids, idle)
        memory = footprint(pids())
        exit_ns = sigterm_to_exit(running.proc.pid, EXIT_TIMEOUT_S)
    finally:
        session.stop(running)
    return _row(load_all, cpu, memory, exit_ns)


def measure_runners(session: Session, count: int, settle: float, idle: float) -> dict:
    lease = session.lease()
    runners = []
    try:
        t0 = time.monotonic_ns()
        for i in range(count):
            runners.append(session.runner(lease.domain_id, node_name=f"hb{i}", params=HEARTBEAT_PARAMS))
        for r in runners:
            r.wait_ready(timeout=120.0)
        load_all = time.monotonic_ns() - t0
        time.sleep(settle)
        cpu = idle_cpu_percent(lambda: [r.pid for r in runners], idle)
        memory = footprint([r.pid for r in runners])
        t1 = time.monotonic_ns()
        for r in runners:
            os.kill(r.pid, signal.SIGTERM)
        gone = all(_exited(r, t1 + int(EXIT_TIMEOUT_S * 1e9)) for r in runners)
        exit_ns = time.monotonic_ns() - t1 if gone else None
    finally:
        for r in runners:
            session.stop_runner(r)
        session.release(lease)
    return _row(load_all, cpu, memory, exit_ns)


def _row(load_all_ns: int, cpu: tuple[float, float], memory: dict, exit_ns: int | None) -> dict:
    """One mode and count's measurements (``cpu``: idle_cpu_percent's)."""
    return {"load_all_ns": load_all_ns, "idle_cpu_pct": cpu[0], "idle_dds_pct": cpu[1],
            "pss_kb": memory["pss_kb"], "exit_ns": exit_ns, "processes": memory["processes"]}  # fmt: skip


def _exited(runner, deadline_ns: int) -> bool:
    try:
        runner.popen.wait(max(0.0, (deadline_ns - time.monotonic_ns()) / 1e9))
        return True
    except subprocess.TimeoutExpired:
        return False


def _ratio(data: dict, a: str, b: str, count: int, key: str) -> float | None:
    """data[a][count][key] ÷ data[b][count][key]; None where either was not measured."""
    x, y = data.get(a, {}).get(count), data.get(b, {}).get(count)
    if not x or not y or x.get(key) is None or not y.get(key):
        return None
    return x[key] / y[key]


def default_goals(data: dict, count: int) -> list[Goal]:
    """The default profile at the size of a real composition (issue 37's
    row, 96 nodes: about Autoware's 84 composables): within 1.5× of what
    the shared profile measured there before it became the default."""
    row = data.get(isolated_default(), {}).get(count, {})
    at, name = f"at {count} nodes", "default profile"

    def value(key: str, scale: float) -> float | None:
        return None if row.get(key) is None else row[key] / scale

    exit_s = value("exit_ns", 1e9)
    if "exit_ns" in row and exit_s is None:  # measured: it did not exit at all
        exit_s = EXIT_TIMEOUT_S
    return [
        goal_at_most(f"{name} load all ≤ 3 s", at, value("load_all_ns", 1e9), 3.0, "s"),
        goal_at_most(f"{name} idle CPU ≤ 15% of a core", at, value("idle_cpu_pct", 1.0), 15.0, "%"),
        goal_at_most(f"{name} PSS ≤ 270 MiB", at, value("pss_kb", 1024.0), 270.0, "MiB"),
        goal_at_most(f"{name} SIGTERM → exit ≤ 2 s", at, exit_s, 2.0, "s"),
    ]


def goals(data: dict, count: int) -> list[Goal]:
    per, shared, thread = "isolated-per-node", "isolated-shared", "thread"
    at = f"at {count} nodes"
    out = [
        goal_ratio_at_most("per-node load all ≤ 2× thread mode's", f"ratio {at}",
                           _ratio(data, per, thread, count, "load_all_ns"), 2.0),
        goal_ratio_at_most("per-node idle CPU ≤ 1.5× shared profile's", f"ratio {at}",
                           _ratio(data, per, shared, count, "idle_cpu_pct"), 1.5),
        goal_ratio_at_most("per-node PSS ≤ 1.5× shared profile's", f"ratio {at}",
                           _ratio(data, per, shared, count, "pss_kb"), 1.5),
    ]  # fmt: skip
    exit_ns = data.get(per, {}).get(count, {}).get("exit_ns")
    out.append(goal_at_most("per-node SIGTERM → exit ≤ 2 s", at, None if exit_ns is None else exit_ns / 1e9, 2.0, "s"))
    cpu = data.get(thread, {}).get(count, {}).get("idle_cpu_pct")
    out.append(goal_at_most("thread mode idle CPU ≤ 30% of a core", at, cpu, 30.0, "%"))
    return out


def run(
    *,
    counts: Sequence[int] = (12, 24, 48),
    modes: Sequence[str] = DEFAULT_MODES,
    settle: float = SETTLE_S,
    idle: float = 10.0,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
    discovery_server: bool = False,
) -> Result:
    counts, modes = sorted(counts), list(modes)
    params: dict[str, object] = {"counts": counts, "modes": modes, "settle": settle, "idle": idle, "out": str(out)}
    name = NAME
    if discovery_server:
        if os.environ.get(ds.VARIABLE):
            raise SystemExit(f"--discovery-server: this process is already under one ({ds.VARIABLE} is set)")
        params["discovery_server"] = True
        name = f"{NAME}-discovery-server"
    session = Session(name, keep_logs=keep_logs)
    server_notes: list[str] = []
    try:
        server = _start_discovery_server(session) if discovery_server else None
        data = _measure_all(session, counts, modes, settle, idle, quiet)
        if server is not None:
            server_notes.append(_server_note(*server))
    finally:
        problems = session.close()
        if discovery_server:  # what this process starts next is under no server
            os.environ.pop(ds.VARIABLE, None)
    goal_list = goals(data, GOAL_NODES if GOAL_NODES in counts else max(counts))
    if isolated_default() in modes:
        goal_list += default_goals(data, DEFAULT_GOAL_NODES if DEFAULT_GOAL_NODES in counts else max(counts))
    under = ", under a discovery server" if discovery_server else ""
    lo, hi = counts[0], counts[-1]
    result = Result(
        name=name,
        title=TITLE + under,
        command=command_line(NAME, {k: v for k, v in params.items() if k != "out"}),
        params=params,
        tables=[_rows_table(data, counts, modes), _growth_table(data, lo, hi, modes)],
        goals=goal_list,
        notes=[
            f"Nodes ×{hi / lo:g} from {lo} to {hi}; a cost that grows linearly grows ×{hi / lo:g} too.",
            f"The picture: {name}.svg beside this file (each measure against the node count, a line a mode).",
            "Modes and counts run one after the other on one machine; this machine is shared and noisy: "
            "compare within one run.",
            *server_notes,
        ],
        summary=[
            summary_row(name, f"{g.goal}", "", None, median=g.measured, goal=g.goal, verdict=g.verdict)
            for g in goal_list
        ],
        raw={"data": {m: {str(c): d for c, d in v.items()} for m, v in data.items()}},
        cleanup=problems,
    )
    result.attachments[f"{name}.svg"] = scale_svg(data, counts, {m: label(m) + under for m in modes})
    return finish(result, out, quiet=quiet)


def _start_discovery_server(session: Session) -> tuple:
    """The benchmark's own server, named in this process's environment
    before its first participant (which reads it); (server, its CPU s so far)."""
    server = session.discovery_server()
    os.environ[ds.VARIABLE] = server.address
    return server, cpu_seconds([server.pid])


def _server_note(server, cpu0: float) -> str:
    """What the server cost over the run (it stops here)."""
    pss_mib, cpu_s = footprint([server.pid])["pss_kb"] / 1024, cpu_seconds([server.pid]) - cpu0
    server.stop()
    return (
        f"Under a discovery server ({ds.VARIABLE}={server.address}): a process of the benchmark's own, "
        f"one rclpy participant as the SERVER, not counted in the rows; at the end its PSS was "
        f"{pss_mib:.0f} MiB, it used {cpu_s:.1f} s of CPU over the whole run, and it knew of up to "
        f"{server.most_nodes()} nodes at once."
    )


def _measure_all(session: Session, counts, modes, settle: float, idle: float, quiet: bool) -> dict:
    """mode -> count -> its row (or {"error": why}), every count one after another."""
    data: dict[str, dict[int, dict]] = {m: {} for m in modes}
    for count in counts:
        for mode in modes:
            try:
                if mode == PROCESS_PER_NODE:
                    data[mode][count] = measure_runners(session, count, settle, idle)
                else:
                    data[mode][count] = measure_container(session, mode, count, settle, idle)
            except AssertionError as exc:  # HarnessTimeout is one: a row that says so, not a lost run
                data[mode][count] = {"error": str(exc).splitlines()[0]}
            if not quiet:
                print(f"{mode} × {count}: {data[mode][count]}", file=sys.stderr, flush=True)
    return data


def _rows_table(data: dict, counts, modes) -> Table:
    table = Table(
        f"{', '.join(map(str, counts))} Heartbeat nodes at 1 Hz (one container, or one runner a node, each)",
        ["mode", "nodes", "load all (s)", "idle CPU (% of a core)", "of it, Fast DDS threads", "PSS (MiB)",
         "SIGTERM → exit (s)", "processes"],
    )  # fmt: skip
    for mode in modes:
        for count in counts:
            d = data[mode][count]
            if "error" in d:
                table.add(label(mode), count, f"failed: {d['error']}", "–", "–", "–", "–", "–")
                continue
            exit_s = "did not exit" if d["exit_ns"] is None else f"{d['exit_ns'] / 1e9:.2f}"
            table.add(label(mode), count, f"{d['load_all_ns'] / 1e9:.2f}", f"{d['idle_cpu_pct']:.1f}",
                      f"{d['idle_dds_pct']:.1f}", f"{d['pss_kb'] / 1024:.0f}", exit_s, d["processes"])  # fmt: skip
    return table


def _growth_table(data: dict, lo: int, hi: int, modes) -> Table:
    growth = Table("Growth: cost at the largest count ÷ cost at the smallest", ["mode", "load all", "idle CPU", "PSS"])
    for mode in modes:
        a, b = data[mode][lo], data[mode][hi]
        growth.add(
            label(mode),
            *(
                fmt_ratio(b[k] / a[k]) if a.get(k) and b.get(k) else "–"
                for k in ("load_all_ns", "idle_cpu_pct", "pss_kb")
            ),
        )
    return growth


def main(argv=None) -> int:
    parser = arg_parser(NAME, __doc__.split("\n\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[12, 24, 48], help="node counts (default 12 24 48)")
    parser.add_argument(
        "--modes", nargs="+", default=DEFAULT_MODES, choices=[*DEFAULT_MODES, "thread-mt", "isolated-shared-glibc"]
    )
    parser.add_argument("--settle", type=float, default=SETTLE_S, help="s after the last load before measuring")
    parser.add_argument("--idle", type=float, default=10.0, help="s of idle over which CPU is measured")
    parser.add_argument(
        "--discovery-server",
        action="store_true",
        help="every participant finds the others through a discovery server of the benchmark's own",
    )
    args = parser.parse_args(argv)
    result = run(counts=args.counts, modes=args.modes, settle=args.settle, idle=args.idle, out=args.out,
                 keep_logs=args.keep_logs, discovery_server=args.discovery_server)  # fmt: skip
    return 0 if not result.cleanup else 1


if __name__ == "__main__":
    sys.exit(main())
