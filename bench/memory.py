"""Marginal memory per node, 1 -> 20 cloneguard::Heartbeat nodes.

    python -m cloneguard.bench.memory                       # 1 -> 20 nodes, every mode
    python -m cloneguard.bench.memory --nodes 40 --settle 2

Modes, one after the other (so one mode's processes never share pages with
another's): isolated per-node profile, isolated shared profile, thread mode,
and process-per-node (one bench.process_per_node runner per node). Nodes are
added one at a time; at 1, 5, 10 and N nodes, after ``--settle`` seconds, the
footprint is sampled three times (median kept).

Footprint = the sum, over the distinct address spaces (mm) of the processes
involved, of /proc/<pid>/smaps_rollup Pss (and Private_* = USS, Rss), plus
the page tables (VmPTE, kernel memory outside PSS). The processes are the
container and every process in its process group (its clone children), or
all the runners. A CLONE_VM child shares the container's mm, so its
smaps_rollup *is* the container's: processes are grouped by mm with
kcmp(KCMP_VM) and each mm counted once; the mm-related fields of
/proc/<pid>/stat (start_code, end_code, start_stack, start_data, end_data,
start_brk, arg/env bounds) are compared as a cross-check.

Marginal per node = (footprint at N - footprint at 1) / (N - 1).
Goal: isolated ≥ 20× smaller per node than process-per-node.
"""

from __future__ import annotations

import statistics
import sys
import time

from cloneguard.harness import procfs

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ratio, ratio
from .goals import goal_at_least_ratio
from .loads import timed_load
from .modes import PROCESS_PER_NODE, label
from .results import Result, Table, summary_row
from .session import Session

NAME = "memory"
TITLE = "Memory: marginal footprint per node"
GOAL_RATIO = 20.0
DEFAULT_MODES = ["isolated-per-node", "isolated-shared", "thread", PROCESS_PER_NODE]
_STAT_MM_FIELDS = (26, 27, 28, 45, 46, 47, 48, 49, 50, 51)  # 1-based, see proc(5)


def rollup(pid: int) -> dict[str, int] | None:
    """/proc/<pid>/smaps_rollup, kB values by key; None if the process is gone."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            lines = f.read().splitlines()[1:]
    except (FileNotFoundError, ProcessLookupError):
        return None
    out = {}
    for line in lines:
        key, _, rest = line.partition(":")
        parts = rest.split()
        if parts and parts[0].isdigit():
            out[key.strip()] = int(parts[0])
    return out or None


def stat_mm_fields(pid: int) -> tuple[int, ...] | None:
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            raw = f.read().decode(errors="replace")
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = raw.rpartition(")")[2].split()  # fields[0] is field 3 (state)
    return tuple(int(fields[n - 3]) for n in _STAT_MM_FIELDS)


def _pte_kb(pid: int) -> int:
    value = procfs.status_field(pid, "VmPTE")
    return int(value.split()[0]) if value else 0


def address_spaces(pids: list[int]) -> list[list[int]]:
    """``pids`` grouped by the mm they run in (kcmp KCMP_VM)."""
    groups: list[list[int]] = []
    for pid in pids:
        for group in groups:
            if procfs.same_address_space(group[0], pid):
                group.append(pid)
                break
        else:
            groups.append([pid])
    return groups


def footprint(pids: list[int]) -> dict:
    live = [p for p in pids if procfs.alive(p)]
    groups = address_spaces(live)
    pss = uss = rss = pte = 0
    stat_agrees = True
    keys = []
    for group in groups:
        fields = {stat_mm_fields(p) for p in group}
        stat_agrees &= len(fields) == 1
        keys.append(next(iter(fields)))
        r = rollup(group[0])
        if r is None:
            continue
        pss += r.get("Pss", 0)
        uss += r.get("Private_Clean", 0) + r.get("Private_Dirty", 0)
        rss += r.get("Rss", 0)
        pte += _pte_kb(group[0])
    stat_agrees &= len(set(keys)) == len(keys)  # distinct mms, distinct fields
    return {
        "processes": len(live),
        "address_spaces": len(groups),
        "pss_kb": pss,
        "uss_kb": uss,
        "rss_kb": rss,
        "pte_kb": pte,
        "stat_fields_agree_with_kcmp": stat_agrees,
    }


def sample(pids_fn, settle: float, samples: int = 3) -> dict:
    time.sleep(settle)
    taken = []
    for i in range(samples):
        if i:
            time.sleep(0.25)
        taken.append(footprint(pids_fn()))
    out = dict(taken[-1])
    for key in ("pss_kb", "uss_kb", "rss_kb", "pte_kb"):
        out[key] = statistics.median(t[key] for t in taken)
    out["stat_fields_agree_with_kcmp"] = all(t["stat_fields_agree_with_kcmp"] for t in taken)
    return out


def checkpoints(nodes: int) -> list[int]:
    return sorted({c for c in (1, 5, 10, nodes) if 1 <= c <= nodes})


def measure_container(session: Session, mode: str, nodes: int, settle: float) -> dict:
    running = session.start(mode)
    points = {}
    try:

        def pids():
            return [running.proc.pid] + [p for p in running.proc.group_members() if p != running.proc.pid]

        for i in range(1, nodes + 1):
            timed_load(running, node_name=f"hb{i}")
            if i in checkpoints(nodes):
                points[i] = sample(pids, settle)
    finally:
        session.stop(running)
    return points


def measure_process_per_node(session: Session, nodes: int, settle: float) -> dict:
    lease = session.lease()
    runners = []
    points = {}
    try:
        for i in range(1, nodes + 1):
            r = session.runner(lease.domain_id, node_name=f"hb{i}")
            runners.append(r)
            r.wait_ready()
            if i in checkpoints(nodes):
                points[i] = sample(lambda: [x.pid for x in runners], settle)
    finally:
        for r in runners:
            session.stop_runner(r)
        session.release(lease)
    return points


def run(
    *,
    nodes: int = 20,
    settle: float = 1.0,
    modes: list[str] = DEFAULT_MODES,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
) -> Result:
    if nodes < 2:
        raise ValueError("--nodes must be at least 2 (the marginal is taken from 1 to N)")
    params = {"nodes": nodes, "settle": settle, "modes": list(modes), "out": str(out)}
    session = Session(NAME, keep_logs=keep_logs)
    data = {}
    try:
        for mode in modes:
            if mode == PROCESS_PER_NODE:
                data[mode] = measure_process_per_node(session, nodes, settle)
            else:
                data[mode] = measure_container(session, mode, nodes, settle)
    finally:
        problems = session.close()

    def mib(kb):
        return kb / 1024

    def marginal(points, key):
        return (points[nodes][key] - points[1][key]) / (nodes - 1)

    ppn_marginal = marginal(data[PROCESS_PER_NODE], "pss_kb") if PROCESS_PER_NODE in data else None
    table = Table(
        f"Footprint, 1 → {nodes} nodes",
        [
            "mode",
            f"processes @{nodes}",
            f"address spaces @{nodes}",
            "PSS @1 (MiB)",
            f"PSS @{nodes} (MiB)",
            "marginal PSS / node (MiB)",
            "marginal USS / node (MiB)",
            "marginal page tables / node (KiB)",
            "process-per-node ÷ this (marginal PSS)",
        ],
    )
    curve = Table("PSS (MiB) by node count", ["mode", *[f"@{c}" for c in checkpoints(nodes)]])
    goals, summary = [], []
    for mode in modes:
        points = data[mode]
        m_pss = marginal(points, "pss_kb")
        table.add(
            label(mode),
            points[nodes]["processes"],
            points[nodes]["address_spaces"],
            f"{mib(points[1]['pss_kb']):.1f}",
            f"{mib(points[nodes]['pss_kb']):.1f}",
            f"{mib(m_pss):.2f}",
            f"{mib(marginal(points, 'uss_kb')):.2f}",
            f"{marginal(points, 'pte_kb'):.0f}",
            fmt_ratio(ratio(ppn_marginal, m_pss)),
        )
        curve.add(label(mode), *[f"{mib(points[c]['pss_kb']):.1f}" for c in checkpoints(nodes)])
        goal_text, verdict = "", ""
        if mode.startswith("isolated") and ppn_marginal is not None:
            g = goal_at_least_ratio(
                "isolated ≥ 20× smaller per node than process-per-node",
                f"{label(mode)}: marginal PSS per node",
                ratio(ppn_marginal, m_pss),
                GOAL_RATIO,
            )
            goals.append(g)
            goal_text = "≥ 20× smaller than process-per-node"
            verdict = f"met ({g.measured})" if g.met else g.verdict
        summary.append(
            summary_row(
                "memory",
                f"marginal PSS per node, 1 → {nodes} nodes",
                label(mode),
                None,
                median=f"{mib(m_pss):.2f} MiB",
                p90="",
                goal=goal_text or "(reference)",
                verdict=verdict,
            )
        )
    mid = 10
    if mid in checkpoints(nodes) and nodes > mid:
        halves = []
        for mode in modes:
            pts = data[mode]
            first = (pts[mid]["pss_kb"] - pts[1]["pss_kb"]) / (mid - 1)
            last = (pts[nodes]["pss_kb"] - pts[mid]["pss_kb"]) / (nodes - mid)
            halves.append(f"{label(mode)} {mib(first):.2f} → {mib(last):.2f}")
        curve_note = (
            f"Marginal PSS per node from 1 → {mid} vs {mid} → {nodes} nodes (MiB): "
            + "; ".join(halves)
            + ". (Not linear where the two differ: the marginal over 1 → N is then an average; "
            "this benchmark does not break the growth down.)"
        )
    else:
        curve_note = "The curve (PSS by node count) is in the second table."
    agree = all(p["stat_fields_agree_with_kcmp"] for pts in data.values() for p in pts.values())
    notes = [
        "Method: processes = the container + every process in its process group (its clone children), "
        "or every runner. They are grouped by address space with kcmp(pid_a, pid_b, KCMP_VM, 0, 0) "
        "(harness.procfs.same_address_space), and /proc/<pid>/smaps_rollup of one member of each group "
        "is summed: a CLONE_VM child's smaps_rollup is the container's mm again and is not counted twice. "
        f"Cross-check with /proc/<pid>/stat's mm fields (code/data/brk/stack/arg/env bounds): "
        f"{'agreed with kcmp in every sample' if agree else 'DISAGREED with kcmp in some sample (see JSON)'}.",
        "PSS divides each shared page by the number of processes mapping it, so the process-per-node "
        "figure charges each runner its share of libpython, rclpy and Fast DDS (other processes on the "
        "host that map the same files, e.g. other containers, lower every share). USS (private pages "
        "only) is the lower bound; page tables (VmPTE) are kernel memory outside PSS, per mm.",
        f"Each point: {settle:g} s after the last node was ready, the median of 3 samples 0.25 s apart. "
        "Heartbeat publishes at 20 Hz; all nodes have distinct names. Each container's domain also holds "
        "the benchmark's client (one more participant for every node's participant to discover); the "
        "runners' domain holds only the runners.",
        curve_note,
        "Isolated per-node: each node brings its own rclpy Context (DDS participant, with its own threads "
        "inside the child) into the shared address space; shared: the nodes are on the container's one "
        "participant and only their executors run in the children. Every clone child also has its own "
        "stack mapping (8 MiB reserved, only touched pages count).",
    ]
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, {"nodes": nodes, "settle": settle, "modes": list(modes)}),
        params,
        [table, curve],
        goals,
        notes,
        summary,
        {"points": {m: {str(k): v for k, v in pts.items()} for m, pts in data.items()}},
        problems,
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--nodes", type=int, default=20, help="nodes at the end (default: %(default)s)")
    parser.add_argument(
        "--settle", type=float, default=1.0, help="seconds to wait before sampling (default: %(default)s)"
    )
    parser.add_argument("--modes", nargs="+", choices=DEFAULT_MODES, default=DEFAULT_MODES)
    opts = parser.parse_args(argv)
    if PROCESS_PER_NODE not in opts.modes:
        parser.error("the goal compares against process-per-node: keep it in --modes")
    result = run(nodes=opts.nodes, settle=opts.settle, modes=opts.modes, out=opts.out, keep_logs=opts.keep_logs)
    return 1 if result.cleanup else 0


if __name__ == "__main__":
    sys.exit(main())
