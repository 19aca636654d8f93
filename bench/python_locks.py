"""Python locks that know their holder (container/isolated/pylocks.c) against
CPython's own: what recording the holder costs.

    python -m cloneguard.bench.python_locks                 # 15 rounds
    python -m cloneguard.bench.python_locks --rounds 31 --ops 400000

In one process, interleaved round by round, the same loop on each type:

uncontended
    one thread, ``with lock: pass`` ``ops`` times (Lock, RLock), and an
    RLock taken twice (recursion);
contended
    ``threads`` threads (2, 4, 8) each doing ``with lock: counter += 1``
    ``ops // threads`` times on one shared lock: the GIL hands the lock
    between them as in a node with a thread pool; how the cost grows with
    the number of threads.

Each figure is nanoseconds per acquire+release, the median over rounds;
the ratio is ours ÷ CPython's of the medians. Goal: ≤ 1.2× in each row.
"""

from __future__ import annotations

import _thread
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import cloneguard.container.isolated._pylocks as _pylocks  # an extension module

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ratio, ratio, stats
from .goals import goal_ratio_at_most
from .results import Result, Table, summary_row

NAME = "python_locks"
TITLE = "Python locks: holder-recording types vs CPython's"
GOAL_RATIO = 1.2
THREADS = (2, 4, 8)
TYPES = {
    "Lock": {"cpython": _thread.allocate_lock, "ours": _pylocks.allocate_lock},
    "RLock": {"cpython": _thread.RLock, "ours": _pylocks.RLock},
}


def _uncontended(lock, ops: int, depth: int) -> int:
    """ns for ``ops`` acquire+release pairs (``depth`` nested each time)."""
    started = time.perf_counter_ns()
    if depth == 1:
        for _ in range(ops):
            with lock:
                pass
    else:
        for _ in range(ops):
            with lock:
                with lock:
                    pass
    return time.perf_counter_ns() - started


def _contended(lock, ops: int, threads: int) -> int:
    """ns for ``threads`` threads to do ``ops`` acquire+release pairs in all."""
    counter = [0]
    start = threading.Barrier(threads + 1)

    def work(n: int) -> None:
        start.wait()
        for _ in range(n):
            with lock:
                counter[0] += 1

    workers = [threading.Thread(target=work, args=(ops // threads,)) for _ in range(threads)]
    for w in workers:
        w.start()
    start.wait()
    started = time.perf_counter_ns()
    for w in workers:
        w.join()
    elapsed = time.perf_counter_ns() - started
    assert counter[0] == ops // threads * threads
    return elapsed


def _contended_case(ops: int, n: int) -> Callable[[Any], float]:
    return lambda lk: _contended(lk, ops, n) / ops


def cases(ops: int) -> dict[str, tuple[str, Callable[[Any], float]]]:
    """case -> (type, fn(lock) -> ns per pair)."""
    out: dict[str, tuple[str, Callable[[Any], float]]] = {
        "uncontended Lock": ("Lock", lambda lk: _uncontended(lk, ops, 1) / ops),
        "uncontended RLock": ("RLock", lambda lk: _uncontended(lk, ops, 1) / ops),
        "uncontended RLock, taken twice": ("RLock", lambda lk: _uncontended(lk, ops, 2) / (2 * ops)),
    }
    for n in THREADS:
        out[f"contended Lock, {n} threads"] = ("Lock", _contended_case(ops, n))
    return out


def measure(rounds: int, ops: int) -> dict:
    """case -> impl -> [ns per pair, one per round]; the implementations
    alternate within a round, in an order that changes round by round."""
    data: dict = {case: {"cpython": [], "ours": []} for case in cases(ops)}
    for r in range(rounds):
        for case, (kind, fn) in cases(ops).items():
            order = ("cpython", "ours") if r % 2 == 0 else ("ours", "cpython")
            for impl in order:
                data[case][impl].append(fn(TYPES[kind][impl]()))
    return data


def run(*, rounds: int = 15, ops: int = 200_000, out=DEFAULT_OUT, keep_logs: bool = False, quiet: bool = False):
    params = {"rounds": rounds, "ops": ops, "out": str(out)}
    switch = sys.getswitchinterval()
    data = measure(rounds, ops)
    table = Table(
        f"ns per acquire+release (median of {rounds} interleaved rounds, {ops} pairs each)",
        ["case", "CPython", "ours", "ours ÷ CPython", "ours p90"],
    )
    goals, summary = [], []
    for case, by in data.items():
        cp, us = stats(by["cpython"]), stats(by["ours"])
        r = ratio(us["median"], cp["median"])
        table.add(case, f"{cp['median']:.1f}", f"{us['median']:.1f}", fmt_ratio(r), f"{us['p90']:.1f}")
        goal = goal_ratio_at_most("≤ 1.2× CPython's", f"{case}: ours ÷ CPython's median", r, GOAL_RATIO)
        goals.append(goal)
        summary.append(
            summary_row(
                "python locks",
                f"{case}: acquire+release",
                "isolated (pylocks)",
                us,
                median=f"{us['median']:.0f} vs {cp['median']:.0f} ns ({fmt_ratio(r)})",
                p90=f"{us['p90']:.0f} ns",
                goal="≤ 1.2× CPython's",
                verdict=goal.verdict,
            )
        )
    notes = [
        "One process, no container: the types are the ones an isolated container installs for "
        "_thread.allocate_lock and _thread.RLock (boot.py); outside a node process they record the holder the "
        "same way.",
        f"Contended rows run under the GIL's switch interval ({switch * 1e3:g} ms): the lock passes between "
        "threads when the GIL does, so they measure the lock's cost under contention, not a parallel speed-up.",
    ]
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, {"rounds": rounds, "ops": ops}),
        params,
        [table],
        goals,
        notes,
        summary,
        data,
        cleanup=[],
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--ops", type=int, default=200_000)
    opts = parser.parse_args(argv)
    run(rounds=opts.rounds, ops=opts.ops, out=opts.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
