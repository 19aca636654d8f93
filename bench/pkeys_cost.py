"""What memory protection keys over node heaps cost: the same per-node
jemalloc container with keys (``--pkeys``) and without (``--no-pkeys``),
side by side in one run.

    python -m cloneguard.bench.pkeys_cost [--n 30] [--count 100] [--pairs 2000000] [--repeat 5]

Three measures, each judged against the goal of at most 5% slower with
keys (ratio of medians):

* LoadNode → LOADED at the client (bench.load_latency's loads, the two
  containers taken in turn);
* intra-process delivery, publish → callback, 1 KiB and 1 MiB plain
  messages between two node processes (bench.intra's source and sink);
* a malloc/free pair of 64 B and 4 KiB in a node process (bench.alloc_guard's
  loops in C: the guard on jemalloc, with CLONEGUARD_PKEYS=1 and without).

Where the CPU or kernel has no keys nothing is measured: the report says
why and judges nothing (the container refuses ``--pkeys`` there)."""

from __future__ import annotations

import statistics
import sys

from .alloc_guard import CONFIGS, KEYED, measure_config
from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ms, ms, stats
from .goals import Goal
from .intra import measure as measure_intra
from .intra import parse_size, summarize
from .load_latency import measure as measure_loads
from .modes import MODES
from .results import Result, Table, summary_row
from .session import Session

NAME = "pkeys_cost"
TITLE = "Protection keys over node heaps: what they cost"
WITHOUT, WITH = "isolated-jemalloc", "isolated-pkeys"
GOAL_PCT = 5.0  # at most 5% slower with keys
GUARD_ON = next(c for c in CONFIGS if c[0] == "jemalloc, guard on")
INTRA_SIZES = ("1KiB", "1MiB")
ALLOC_MEASURES = ("pair 64 B, node process", "pair 4096 B, node process")


def keys_missing() -> str | None:
    """Why keys cannot be measured here, or None."""
    from cloneguard.container.isolated import pkeys

    return pkeys.probe().unavailable


def judge(measure: str, without: float | None, with_keys: float | None) -> Goal:
    goal = f"≤ {GOAL_PCT:g}% slower with keys"
    if not without or with_keys is None:
        return Goal(goal, measure, "–", None, "not measured")
    pct = 100.0 * (with_keys / without - 1.0)
    shown = f"{pct:+.1f}%"
    if pct <= GOAL_PCT:
        return Goal(goal, measure, shown, True, f"met ({shown})")
    return Goal(goal, measure, shown, False, f"missed: {shown} against ≤ {GOAL_PCT:g}%")


def measure(n: int, count: int, pairs: int, repeat: int, keep_logs: bool) -> tuple[dict, list[str]]:
    """Medians (ms for the container's measures, ns for malloc/free) by
    measure and side, and the sessions' clean-up problems."""
    figures: dict[str, dict[str, float | None]] = {}
    session = Session(NAME, keep_logs=keep_logs)
    try:
        loads = measure_loads(session, [WITHOUT, WITH], n)
        figures["LoadNode → LOADED at client (ms)"] = {
            mode: stats(ms(loads[mode]["loaded"]))["median"] for mode in (WITHOUT, WITH)
        }
        p = {
            "count": count, "warmup": 5, "period": 0.02, "large_period": 0.1, "dds_large_period": 0.5,
            "dds_large_count": 20, "burst": 2, "burst_bytes": 1 << 30, "burst_seconds": 0.5, "settle": 0.5,
        }  # fmt: skip
        sizes = [parse_size(s) for s in INTRA_SIZES]
        for mode in (WITHOUT, WITH):
            data = measure_intra(session, sizes, ["intra-plain"], p, floor=False, mode=mode)
            for size_name, size in zip(INTRA_SIZES, sizes, strict=True):
                key = f"intra-process delivery, {size_name} plain message: publish → callback (ms)"
                figures.setdefault(key, {})[mode] = summarize(data[(size, "intra-plain")])["latency"]["median"]
    finally:
        problems = session.close()
    for mode, config in ((WITHOUT, GUARD_ON), (WITH, KEYED)):
        raw = measure_config(*config, pairs, max(pairs // 10, 1000), repeat)
        for m in ALLOC_MEASURES:
            figures.setdefault(f"malloc/free {m.removeprefix('pair ')} (ns)", {})[mode] = statistics.median(raw[m])
    return figures, problems


def run(
    *,
    n: int = 30,
    count: int = 100,
    pairs: int = 2_000_000,
    repeat: int = 5,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
) -> Result:
    args = {"n": n, "count": count, "pairs": pairs, "repeat": repeat}
    why = keys_missing()
    figures, problems = ({}, []) if why else measure(n, count, pairs, repeat, keep_logs)
    table = Table(
        "Medians, without keys and with them (one run, side by side)",
        ["measure", MODES[WITHOUT][0], MODES[WITH][0], "with keys", "verdict"],
    )
    goals, summary = [], []
    for measure_name, side in figures.items():
        goal = judge(measure_name, side.get(WITHOUT), side.get(WITH))
        goals.append(goal)
        table.add(measure_name, fmt_ms(side.get(WITHOUT)), fmt_ms(side.get(WITH)), goal.measured, goal.verdict)
        summary.append(
            summary_row(
                "protection keys",
                measure_name,
                f"{MODES[WITH][0]} vs {MODES[WITHOUT][0]}",
                None,
                median=f"{fmt_ms(side.get(WITH))} vs {fmt_ms(side.get(WITHOUT))} ({goal.measured})",
                goal=goal.goal,
                verdict=goal.verdict,
            )
        )
    if why:
        summary.append(
            summary_row("protection keys", "cost of keys", MODES[WITH][0], None, verdict=f"not measured: {why}")
        )
    notes = (
        [f"Not measured on this machine: {why}."]
        if why
        else [
            "LoadNode → LOADED: cloneguard::Heartbeat loaded and unloaded in each container in turn "
            f"(n={n} each, bench.load_latency).",
            f"Intra-process: bench::PayloadSource → bench::PayloadSink, {count} messages a size, one per "
            "20 ms (1 MiB: 100 ms), in two node processes of one container (bench.intra).",
            "malloc/free: bench.alloc_guard's worker, a node process of a CloneCore with the guard on "
            "jemalloc, keys asked for by CLONEGUARD_PKEYS=1 as the container does.",
        ]
    )
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, args),
        args | {"out": str(out)},
        [table],
        goals,
        notes,
        summary,
        {"medians": figures, "not_measured": why},
        problems,
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--n", type=int, default=30, help="loads per container (default: %(default)s)")
    parser.add_argument("--count", type=int, default=100, help="messages per size (default: %(default)s)")
    parser.add_argument("--pairs", type=int, default=2_000_000, help="malloc/free pairs (default: %(default)s)")
    parser.add_argument("--repeat", type=int, default=5, help="malloc/free repeats (default: %(default)s)")
    opts = parser.parse_args(argv)
    run(n=opts.n, count=opts.count, pairs=opts.pairs, repeat=opts.repeat, out=opts.out, keep_logs=opts.keep_logs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
