"""Scale: how the cost of each mode grows with the number of nodes.

    python -m cloneguard.bench.scale                          # 12, 24, 48 nodes, every mode
    python -m cloneguard.bench.scale --counts 12 24 48 96 --idle 10

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
≤ 2 s; thread mode idle CPU ≤ 30% of a core.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from cloneguard.harness import procfs

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ratio
from .goals import Goal, goal_at_most, goal_ratio_at_most
from .loads import timed_load
from .memory import footprint
from .modes import HEARTBEAT_PARAMS, PROCESS_PER_NODE, label
from .results import Result, Table, summary_row
from .scale_chart import scale_svg
from .session import Session
from .shutdown import sigterm_to_exit

NAME = "scale"
TITLE = "Scale: N nodes at 1 Hz, per mode"
DEFAULT_MODES = ["thread", "isolated-shared", "isolated-mixed", "isolated-per-node", PROCESS_PER_NODE]
GOAL_NODES = 48
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


def idle_cpu_percent(pids_fn, seconds: float) -> float:
    """CPU the processes used over ``seconds``, as % of one core."""
    pids = pids_fn()
    t0, c0 = time.monotonic(), cpu_seconds(pids)
    time.sleep(seconds)
    c1, t1 = cpu_seconds(pids), time.monotonic()
    return 100.0 * (c1 - c0) / (t1 - t0)


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
    return {"load_all_ns": load_all, "idle_cpu_pct": cpu, "pss_kb": memory["pss_kb"], "exit_ns": exit_ns,
            "processes": memory["processes"]}  # fmt: skip


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
    return {"load_all_ns": load_all, "idle_cpu_pct": cpu, "pss_kb": memory["pss_kb"], "exit_ns": exit_ns,
            "processes": memory["processes"]}  # fmt: skip


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
    counts: list[int] = (12, 24, 48),
    modes: list[str] = DEFAULT_MODES,
    settle: float = SETTLE_S,
    idle: float = 10.0,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
) -> Result:
    counts, modes = sorted(counts), list(modes)
    params = {"counts": counts, "modes": modes, "settle": settle, "idle": idle, "out": str(out)}
    session = Session(NAME, keep_logs=keep_logs)
    data: dict[str, dict[int, dict]] = {m: {} for m in modes}
    try:
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
    finally:
        problems = session.close()

    table = Table(
        f"{', '.join(map(str, counts))} Heartbeat nodes at 1 Hz (one container, or one runner a node, each)",
        ["mode", "nodes", "load all (s)", "idle CPU (% of a core)", "PSS (MiB)", "SIGTERM → exit (s)", "processes"],
    )
    for mode in modes:
        for count in counts:
            d = data[mode][count]
            if "error" in d:
                table.add(label(mode), count, f"failed: {d['error']}", "–", "–", "–", "–")
                continue
            exit_s = "did not exit" if d["exit_ns"] is None else f"{d['exit_ns'] / 1e9:.2f}"
            table.add(label(mode), count, f"{d['load_all_ns'] / 1e9:.2f}", f"{d['idle_cpu_pct']:.1f}",
                      f"{d['pss_kb'] / 1024:.0f}", exit_s, d["processes"])  # fmt: skip
    judged = GOAL_NODES if GOAL_NODES in counts else max(counts)
    goal_list = goals(data, judged)
    growth = Table("Growth: cost at the largest count ÷ cost at the smallest", ["mode", "load all", "idle CPU", "PSS"])
    lo, hi = counts[0], counts[-1]
    for mode in modes:
        a, b = data[mode][lo], data[mode][hi]
        growth.add(
            label(mode),
            *(
                fmt_ratio(b[k] / a[k]) if a.get(k) and b.get(k) else "–"
                for k in ("load_all_ns", "idle_cpu_pct", "pss_kb")
            ),
        )
    svg = scale_svg(data, counts, {m: label(m) for m in modes})
    result = Result(
        name=NAME,
        title=TITLE,
        command=command_line(NAME, {k: v for k, v in params.items() if k != "out"}),
        params=params,
        tables=[table, growth],
        goals=goal_list,
        notes=[
            f"Nodes ×{hi / lo:g} from {lo} to {hi}; a cost that grows linearly grows ×{hi / lo:g} too.",
            "The picture: scale.svg beside this file (each measure against the node count, a line a mode).",
            "Modes and counts run one after the other on one machine; this machine is shared and noisy: "
            "compare within one run.",
        ],
        summary=[
            summary_row(NAME, f"{g.goal}", "", None, median=g.measured, goal=g.goal, verdict=g.verdict)
            for g in goal_list
        ],
        raw={"data": {m: {str(c): d for c, d in v.items()} for m, v in data.items()}},
        cleanup=problems,
    )
    result.attachments["scale.svg"] = svg
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, __doc__.split("\n\n")[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[12, 24, 48], help="node counts (default 12 24 48)")
    parser.add_argument("--modes", nargs="+", default=DEFAULT_MODES, choices=DEFAULT_MODES + ["thread-mt"])
    parser.add_argument("--settle", type=float, default=SETTLE_S, help="s after the last load before measuring")
    parser.add_argument("--idle", type=float, default=10.0, help="s of idle over which CPU is measured")
    args = parser.parse_args(argv)
    result = run(counts=args.counts, modes=args.modes, settle=args.settle, idle=args.idle, out=args.out,
                 keep_logs=args.keep_logs)  # fmt: skip
    return 0 if not result.cleanup else 1


if __name__ == "__main__":
    sys.exit(main())
