"""What memory protection keys over node heaps cost: A, keys on
(``--isolated --jemalloc --pkeys``: what ``--isolated --jemalloc`` is by
default on a CPU with keys, made a refusal rather than a silent "off"
where there are none), against B, keys off (``--isolated --jemalloc
--no-pkeys``), in interleaved pairs.

    python -m cloneguard.bench.pkeys_cost [--n 25] [--loads 20] [--count 100] [--period 0.005]
                                          [--pairs 2000000] [--repeat 5] [--steps 500] [--cpu N]

The goal: at most 5% slower with keys, on LoadNode, intra-process delivery
and malloc/free. One run of each side cannot tell 5% on this project's
machines (issue 35: the old side-by-side run, twice on one PKU machine,
gave malloc/free 4 KiB -27% then +80%): what separates two runs minutes
apart on a shared 2-core VM with other work on it is many times 5%. So:

* Pairs, interleaved. A run is ``--n`` pairs. Each pair is a fresh A
  container and a fresh B container (LoadNode, intra-process delivery) and
  a fresh A worker process and a fresh B worker process (malloc/free): the
  pairs are independent of one another (what a container or process
  happens to get, its memory layout, its slots, is inside one pair, not
  shared by all). Within a pair A and B are measured back to back, and
  which goes first alternates (A, B, then B, A ...), within the pair and
  from pair to pair, so drift and other engineers' load fall on both
  alike. Interleaving is the defence against a noisy machine: nothing here
  needs it quiet.
* On one CPU (``--cpu``, by default the last this process may use; -1: on
  any): the containers and workers of the pairs inherit the benchmark's
  affinity. In this VM a wake-up across CPUs sometimes costs ~0.2 ms more,
  two to three times an intra-process delivery, in spells that come and
  go between runs: on both CPUs the 1 KiB intra-process interval of 24
  pairs was -33% … +25%, on one +4.6% … +17%. Keys cost work (instructions, PKRU
  writes), which one CPU keeps; what it takes out is the VM's wake-ups.
* Per pair, per measure: A's figure and B's (the median of that pair's
  samples) and their ratio A / B.
* Per measure: the median of the per-pair ratios with its 95% interval,
  the distribution-free interval for a median from order statistics (the
  sign test's: x(k) … x(n+1-k) of the sorted ratios, k the largest with
  P(Binomial(n, 1/2) < k) ≤ 2.5%; its exact coverage, ≥ 95%, is given).
  It assumes only that the pairs are independent: no normality, and a wild
  pair moves it by one rank at most. From 6 pairs on; 25 give x(8) … x(18)
  (95.7%).
* Verdict: met if the whole interval is at or below +5%, missed if all of
  it is above, undecided otherwise (more pairs narrow it: ``--n``).
* Instructions, for malloc/free, which settle what time cannot. This VM
  has no hardware counters (``perf stat -e instructions``: "<not
  supported>"; its kernel: "no PMU driver, software events only"), and
  valgrind cannot run the keyed path (its synthetic CPU has no PKU, so the
  guard starts without keys; nor does it decode WRPKRU). So the benchmark
  counts them itself: it single-steps (ptrace) the node process through
  ``hammer_pairs`` on the real CPU, one step an instruction, and takes the
  count for 100 + ``--steps`` malloc/free pairs less the count for 100,
  divided by ``--steps``. Deterministic; the same for A and B but for what
  keys add.

Measures:

* LoadNode → LOADED at the client: a cloneguard::Heartbeat loaded and
  unloaded ``--loads`` times in each of the pair's containers, A and B in
  turn (a first load in each, which imports the module, left out).
* Intra-process delivery, publish → callback: 1 KiB and 1 MiB plain
  messages from a bench::PayloadSource to a bench::PayloadSink in two node
  processes (bench.intra's run), ``--count`` messages one per ``--period``,
  once in A and once in B per pair.
* malloc/free of 64 B and 4 KiB in a node process: faults/hammer.c's loop
  (``--pairs`` pairs, ``--repeat`` times a size) in a child of a CloneCore
  with the guard on jemalloc, keys asked for by CLONEGUARD_PKEYS=1 as the
  container does (A) or not (B); each worker says which keys it holds, and
  the run stops unless every A worker held some and no B worker did.

Where the CPU or kernel has no keys nothing is measured: the report says
why and judges nothing (the container refuses ``--pkeys`` there)."""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time

from cloneguard.harness.process import REPO_ROOT, stop_group

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ms, median_interval, pct
from .goals import Goal, goal_median_ratio
from .modes import MODES
from .results import Result, Table, summary_row
from .stepping import step_calls

NAME = "pkeys_cost"
TITLE = "Protection keys over node heaps: what they cost (interleaved pairs)"
KEYS_ON, KEYS_OFF = "isolated-pkeys", "isolated-jemalloc"  # A, B
SIDES = {"A": KEYS_ON, "B": KEYS_OFF}
GOAL_PCT = 5.0  # at most 5% slower with keys
LIMIT = 1.0 + GOAL_PCT / 100.0
INTRA_SIZES = ("1KiB", "1MiB")
SIZES = (64, 4096)  # malloc/free
STEP_BASE = 100  # pairs in the shorter of the two single-stepped calls
LOAD = "LoadNode → LOADED at client (ms)"
INTRA = {s: f"intra-process delivery, {s} plain message: publish → callback (ms)" for s in INTRA_SIZES}
ALLOC = {size: f"malloc/free {size} B, node process (ns)" for size in SIZES}
MEASURES = [LOAD, *INTRA.values(), *ALLOC.values()]


def keys_missing() -> str | None:
    """Why keys cannot be measured here, or None."""
    from cloneguard.container.isolated import pkeys

    return pkeys.probe().unavailable


def judge(measure: str, ratios: list[float]) -> Goal:
    return goal_median_ratio(f"≤ {GOAL_PCT:g}% slower with keys (95% interval)", measure, ratios, LIMIT)


def judge_instructions(measure: str, a: float | None, b: float | None) -> Goal:
    goal = f"≤ {GOAL_PCT:g}% more instructions with keys"
    if not a or not b:
        return Goal(goal, measure, "–", None, "not measured")
    r = a / b
    shown = f"{a:.1f} vs {b:.1f} ({pct(r)})"
    return Goal(goal, measure, shown, r <= LIMIT, "met" if r <= LIMIT else f"missed: {pct(r)}")


# -- malloc/free: the worker and the single-stepper ---------------------------
def _worker(argv: list[str]) -> int:
    """In a process of its own (LD_PRELOAD: the guard and jemalloc):
    ``time PAIRS REPEAT`` prints ns per malloc/free pair in a node process,
    by size; ``step N1 N2`` prints the node process's pid and the entry of
    hammer_pairs, warms up, waits for a byte on stdin (the tracer has
    attached), then calls hammer_pairs(size, N1) and (size, N2) for each size
    through a function pointer (the cffi wrapper inlines it)."""
    from cloneguard.container import allocator

    allocator.glibc_arena_per_task()
    from cloneguard.container.isolated import pkeys
    from cloneguard.container.isolated.core import CloneCore
    from cloneguard.faults._hammer import ffi, lib

    kind, x, y = argv[0], int(argv[1]), int(argv[2])
    out: dict = {}
    with CloneCore(alloc_guard=True) as core:
        keys = pkeys.heap_keys()
        out["keys"] = keys if isinstance(keys, list) else []
        if kind == "time":
            pairs, repeat = x, y

            def loops() -> None:
                for _ in range(repeat):
                    for size in SIZES:
                        out.setdefault(str(size), []).append(lib.hammer_pairs(size, pairs) / pairs)

            child = core.spawn(loops)
        else:
            fn = ffi.cast("int64_t(*)(size_t, long)", ffi.addressof(lib, "hammer_pairs"))

            def stepped() -> None:
                for size in SIZES:
                    lib.hammer_pairs(size, 10_000)  # jemalloc's tcache, the guard's caller cache
                os.read(0, 1)
                for size in SIZES:
                    for n in (x, y):
                        fn(size, n)

            child = core.spawn(stepped)
            print(json.dumps({"pid": child.pid, "entry": int(ffi.cast("uintptr_t", fn))}), flush=True)
        death = core.wait(child, 1800)
        if death is None or death.exit_code != 0:
            raise SystemExit(f"the node process ended with {death}")
        core.release(child)
    print(json.dumps(out), flush=True)
    return 0


def _worker_env(side: str) -> dict:
    from cloneguard.container import allocator

    env = dict(os.environ)
    env["LD_PRELOAD"] = f"{allocator.GUARD_PATH} {allocator.jemalloc_path() or ''}"
    if side == "A":
        env["CLONEGUARD_PKEYS"] = "1"  # what the container's --pkeys sets (heapkeys.c)
    else:
        env.pop("CLONEGUARD_PKEYS", None)
    return env


def _start_worker(side: str, args: list[str], stdin=subprocess.DEVNULL) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "cloneguard.bench.pkeys_cost", "--worker", *args],
        cwd=REPO_ROOT,
        env=_worker_env(side),
        stdin=stdin,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )


def _finish_worker(proc: subprocess.Popen, what: str, timeout: float) -> dict:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        stop_group(proc, proc.pid, 1.0)
        raise RuntimeError(f"{what}: no answer within {timeout:g} s") from None
    stop_group(proc, proc.pid, 1.0)  # whatever it left in its group
    if proc.returncode != 0:
        raise RuntimeError(f"{what} exited with {proc.returncode}:\n{err.decode(errors='replace')[-3000:]}")
    return json.loads(out.decode().strip().splitlines()[-1])


def time_alloc(side: str, pairs: int, repeat: int) -> dict:
    """ns per malloc/free pair by size (``repeat`` loops each) and the keys held."""
    return _finish_worker(_start_worker(side, ["time", str(pairs), str(repeat)]), f"malloc/free worker {side}", 1800)


def count_steps(side: str, steps: int, max_steps: int = 50_000_000) -> dict:
    """Instructions per malloc/free pair by size, counted by single-stepping
    the node process through hammer_pairs(size, N) from its first
    instruction to its return: (count(N2) - count(N1)) / (N2 - N1)."""
    n1, n2 = STEP_BASE, STEP_BASE + steps
    proc = _start_worker(side, ["step", str(n1), str(n2)], stdin=subprocess.PIPE)
    try:
        counts, _ = step_calls(proc, f"step worker {side}", 2 * len(SIZES), max_steps=max_steps)
        done = _finish_worker(proc, f"step worker {side}", 120)
    except BaseException:
        stop_group(proc, proc.pid, 1.0)
        raise
    per_op = {str(size): (counts[2 * i + 1] - counts[2 * i]) / steps for i, size in enumerate(SIZES)}
    return {"per_op": per_op, "counts": counts, "n": [n1, n2], "keys": done["keys"]}


# -- the pairs ---------------------------------------------------------------
def _load_ms(running, name: str) -> float:
    from .loads import timed_load, timed_unload

    trial = timed_load(running, node_name=name)
    timed_unload(running, trial.unique_id)
    return trial.loaded_ns / 1e6


def measure(
    n: int, loads: int, count: int, period: float, pairs: int, repeat: int, keep_logs: bool, cpu: int | None
) -> tuple[list[dict], list[str]]:
    """Per pair: its order and, by measure, A's samples and B's; and the
    clean-up problems."""
    from .intra import parse_size, plan, run_pair
    from .session import Session

    p = {
        "count": count, "warmup": 5, "period": period, "large_period": period, "dds_large_period": 0.5,
        "dds_large_count": 20, "burst": 2, "burst_bytes": 1 << 30, "burst_seconds": 0.2, "settle": 0.2,
    }  # fmt: skip
    pairs_out: list[dict] = []

    def order(i: int, j: int) -> tuple[str, str]:
        """Which side goes first at the j-th measurement of pair i: A, B
        and B, A in turn, within a pair and from one pair to the next."""
        return ("A", "B") if (i + j) % 2 == 0 else ("B", "A")

    saved = os.sched_getaffinity(0)
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})  # what this process starts from now on inherits it
    session = Session(NAME, keep_logs=keep_logs)
    try:
        for i in range(n):
            t0 = time.monotonic()
            marks: list[tuple[str, float]] = [("", t0)]

            rec: dict = {"first": order(i, 0)[0], "errors": []}
            data: dict[str, dict[str, list[float]]] = {m: {"A": [], "B": []} for m in MEASURES}
            started = {side: session.start(SIDES[side]) for side in order(i, 0)}
            marks.append(("start", time.monotonic()))
            try:
                for side in order(i, 0):
                    _load_ms(started[side], f"cold{i}")  # imports the module: left out
                for k in range(loads):
                    for side in order(i, k):
                        data[LOAD][side].append(_load_ms(started[side], f"hb{i}_{k}"))
                marks.append(("loads", time.monotonic()))
                for s, size_name in enumerate(INTRA_SIZES):
                    size = parse_size(size_name)
                    for side in order(i, s):
                        d = run_pair(started[side], 10 * s + (side == "B"), plan(size, "intra-plain", p), p)
                        if d["error"]:
                            rec["errors"].append(f"pair {i}, {side}, {size_name}: {d['error']}")
                        else:
                            data[INTRA[size_name]][side] = [v / 1e3 for v in d["sink"]["latency_us"]]
                marks.append(("intra", time.monotonic()))
            finally:
                for side in order(i, 0):
                    session.stop(started[side])
            keys = {}
            for side in order(i, 1):
                got = time_alloc(side, pairs, repeat)
                keys[side] = got["keys"]
                for size in SIZES:
                    data[ALLOC[size]][side] = got[str(size)]
            if not keys["A"] or keys["B"]:
                raise RuntimeError(f"malloc/free workers: keys A {keys['A']}, B {keys['B']} (A needs some, B none)")
            marks.append(("stop, malloc/free", time.monotonic()))
            rec["samples"] = data
            rec["phases"] = {name: round(t - marks[j][1], 2) for j, (name, t) in enumerate(marks[1:])}
            rec["seconds"] = round(time.monotonic() - t0, 2)
            pairs_out.append(rec)
    finally:
        problems = session.close()
        os.sched_setaffinity(0, saved)
    return pairs_out, problems


def figures(pairs: list[dict]) -> dict[str, dict]:
    """By measure: per-pair values of each side (the median of its samples),
    per-pair ratios, and the pairs left out (a side without samples)."""
    out = {}
    for m in MEASURES:
        a, b, r, skipped = [], [], [], 0
        for rec in pairs:
            sa, sb = rec["samples"][m]["A"], rec["samples"][m]["B"]
            if not sa or not sb:
                skipped += 1
                continue
            ma, mb = statistics.median(sa), statistics.median(sb)
            a.append(ma)
            b.append(mb)
            r.append(ma / mb)
        out[m] = {"A": a, "B": b, "ratios": r, "skipped": skipped}
    return out


def run(
    *,
    n: int = 25,
    loads: int = 20,
    count: int = 100,
    period: float = 0.005,
    pairs: int = 2_000_000,
    repeat: int = 5,
    steps: int = 500,
    cpu: int | None = None,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
) -> Result:
    args = {
        "n": n, "loads": loads, "count": count, "period": period, "pairs": pairs, "repeat": repeat, "steps": steps,
    }  # fmt: skip
    if cpu is None:  # the last CPU this process may use; -1: none
        cpu = max(os.sched_getaffinity(0))
    args["cpu"] = cpu
    pin = cpu if cpu >= 0 else None
    why = keys_missing()
    t0 = time.monotonic()
    pair_data, problems = ([], []) if why else measure(n, loads, count, period, pairs, repeat, keep_logs, pin)
    instr: dict[str, dict] = {}
    uncounted = None  # why the instructions were not counted
    if not why and steps > 0:
        try:
            for side in ("A", "B"):
                instr[side] = count_steps(side, steps)
        except OSError as exc:  # ptrace refused (Yama, a seccomp filter, no CAP_SYS_PTRACE ...)
            instr, uncounted = {}, str(exc)
    seconds = time.monotonic() - t0
    figs = figures(pair_data)

    label_a, label_b = MODES[KEYS_ON][0], MODES[KEYS_OFF][0]
    table = Table(
        f"A (keys on) against B (keys off): {n} interleaved pairs",
        [
            "measure",
            "pairs",
            "A: median",
            "B: median",
            "A ÷ B: median of the pairs' ratios",
            "95% interval",
            "verdict (≤ +5%)",
        ],
    )
    goals, summary = [], []
    for m in MEASURES if not why else []:
        f = figs[m]
        goal = judge(m, f["ratios"])
        goals.append(goal)
        ci = median_interval(f["ratios"])
        fmt = fmt_ms if m in (LOAD, *INTRA.values()) else (lambda x: f"{x:.1f}")
        med_a = fmt(statistics.median(f["A"])) if f["A"] else "–"
        med_b = fmt(statistics.median(f["B"])) if f["B"] else "–"
        table.add(
            m,
            len(f["ratios"]),
            med_a,
            med_b,
            pct(statistics.median(f["ratios"])) if f["ratios"] else "–",
            f"{pct(ci[0])} … {pct(ci[1])} ({100 * ci[2]:.1f}%)" if ci else "– (fewer than 6 pairs)",
            goal.verdict,
        )
        summary.append(
            summary_row(
                "protection keys",
                m,
                f"{label_a} vs {label_b}",
                None,
                median=f"{med_a} vs {med_b} ({goal.measured})",
                goal=goal.goal,
                verdict=goal.verdict,
            )
        )
    tables = [table]
    if instr:
        t2 = Table(
            f"Instructions per malloc/free pair in a node process (single-stepped, {steps} pairs)",
            ["measure", "A: keys on", "B: keys off", "A − B", "A ÷ B", "verdict (≤ +5%)"],
        )
        for size in SIZES:
            a, b = instr["A"]["per_op"][str(size)], instr["B"]["per_op"][str(size)]
            m = f"malloc/free {size} B, node process (instructions)"
            goal = judge_instructions(m, a, b)
            goals.append(goal)
            t2.add(m, f"{a:.1f}", f"{b:.1f}", f"{a - b:+.1f}", pct(a / b), goal.verdict)
            summary.append(
                summary_row(
                    "protection keys",
                    m,
                    f"{label_a} vs {label_b}",
                    None,
                    median=goal.measured,
                    goal=goal.goal,
                    verdict=goal.verdict,
                )
            )
        tables.append(t2)
    if why:
        summary.append(summary_row("protection keys", "cost of keys", label_a, None, verdict=f"not measured: {why}"))
    left_out = {m: figs[m]["skipped"] for m in MEASURES if figs.get(m, {}).get("skipped")}
    errors = [e for rec in pair_data for e in rec["errors"]]
    notes = (
        [f"Not measured on this machine: {why}."]
        if why
        else [
            f"A: `{' '.join(MODES[KEYS_ON][1])}`; B: `{' '.join(MODES[KEYS_OFF][1])}`. Each pair: a fresh A "
            "and a fresh B container, then a fresh A and a fresh B malloc/free worker; within it A and B "
            "back to back, the first of the two alternating. The run took "
            f"{seconds:.0f} s" + (f", its pairs on CPU {pin} alone." if pin is not None else ", its pairs on any CPU."),
            f"LoadNode: cloneguard::Heartbeat loaded and unloaded {loads} times in each container of a pair "
            "(its first, cold load left out); the pair's figure for a side is the median of its loads.",
            f"Intra-process: bench::PayloadSource → bench::PayloadSink (bench.intra), {count} messages "
            f"one per {period * 1e3:g} ms in each container of a pair; the side's figure is the median latency.",
            f"malloc/free: faults/hammer.c's hammer_pairs, {pairs} pairs {repeat} times a size in a node "
            "process of a CloneCore with the guard on jemalloc, in a fresh worker per side and pair "
            "(CLONEGUARD_PKEYS=1 for A; every A worker held keys, no B worker did); the side's figure is "
            "the median of its loops.",
            "A ÷ B: the median of the per-pair ratios; its 95% interval is the sign test's "
            "(order statistics x(k) … x(n+1-k) of the n sorted ratios, distribution-free, exact coverage "
            "in brackets); met if the whole interval is ≤ +5%, missed if all of it is above, undecided "
            "otherwise.",
            *(
                [
                    "Instructions: the node process single-stepped (ptrace) through hammer_pairs, each step "
                    "one instruction retired (a rep-prefixed one counts once per iteration); per pair = "
                    f"(count for {STEP_BASE + steps} pairs − count for {STEP_BASE}) / {steps}. Exact, and "
                    "on the real CPU: no hardware counter needed (perf stat has none in a VM without a "
                    "virtual PMU), and the keyed path itself (valgrind's synthetic CPU has no PKU)."
                ]
                if instr
                else []
            ),
            *([f"Instructions not counted: {uncounted}."] if uncounted else []),
            *([f"Pairs left out (a side failed): {left_out}; why: {errors}."] if left_out or errors else []),
        ]
    )
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, args),
        args | {"out": str(out)},
        tables,
        goals,
        notes,
        summary,
        {"pairs": pair_data, "instructions": instr, "not_counted": uncounted, "seconds": seconds, "not_measured": why},
        problems,
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        return _worker(argv[1:])
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--n", type=int, default=25, help="interleaved A/B pairs (default: %(default)s)")
    parser.add_argument(
        "--loads", type=int, default=20, help="LoadNodes per container of a pair (default: %(default)s)"
    )
    parser.add_argument("--count", type=int, default=100, help="messages per size and container (default: %(default)s)")
    parser.add_argument("--period", type=float, default=0.005, help="s between messages (default: %(default)s)")
    parser.add_argument(
        "--pairs", type=int, default=2_000_000, help="malloc/free pairs per timed loop (default: %(default)s)"
    )
    parser.add_argument("--repeat", type=int, default=5, help="timed loops per size and worker (default: %(default)s)")
    parser.add_argument(
        "--steps", type=int, default=500, help="malloc/free pairs stepped, 0: none (default: %(default)s)"
    )
    parser.add_argument(
        "--cpu",
        type=int,
        default=None,
        help="run the pairs on this CPU alone, -1: on any (default: the last this process may use)",
    )
    opts = parser.parse_args(argv)
    run(
        n=opts.n,
        loads=opts.loads,
        count=opts.count,
        period=opts.period,
        pairs=opts.pairs,
        repeat=opts.repeat,
        steps=opts.steps,
        cpu=opts.cpu,
        out=opts.out,
        keep_logs=opts.keep_logs,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
