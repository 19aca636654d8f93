"""What the allocator guard's memory accounting costs (issue 40: at most
2% on the allocator benchmarks): A, a guard without it, against B, a
guard with it, the same everything else, malloc/free in a node process.

    python -m cloneguard.bench.accounting_cost --a TREE [--b TREE] [--n 20] [--repeat 5] [--steps 1000] [--cpu N]

A and B are source trees of this project with their C extensions built in
place, e.g. A the parent of the commit that added the accounting (618dd6b,
"Per-node memory budgets"), B this checkout (the default)::

    git worktree add --detach /tmp/wt-before 618dd6b~1
    (cd /tmp/wt-before && python setup.py build_ext --inplace)
    python -m cloneguard.bench.accounting_cost --a /tmp/wt-before

Each measurement runs in a fresh worker process with its side's guard
preloaded (LD_PRELOAD: TREE/container/isolated/_allocguard*.so, then
jemalloc for the jemalloc rows) and its side's ``cloneguard.container``
imported from TREE (the clone core the guard is started by must be the
guard's own: they are built against one another); the loop, the
benchmark and everything else come from this checkout. In the worker a
CloneCore with the guard on spawns one node process (a clone child bound
to a slot), which runs faults/hammer.c's ``hammer_pairs(size, n)``: n
times ``free(malloc(size))``, in C. Sizes 64 B (glibc's tcache, jemalloc's
thread cache), 4 KiB (glibc's arena) and 256 KiB (above the guard's fixed
glibc mmap threshold, allocator.MMAP_THRESHOLD = 128 KiB: each block
mmapped and unmapped, through the guard's big-block table; jemalloc's
large size classes), under glibc's malloc and under jemalloc.

* Instructions (exact): the node process single-stepped (ptrace) through
  hammer_pairs, one step an instruction (this VM has no hardware
  counters: ``perf stat -e instructions:u`` says "<not supported>"), on
  the real CPU, with pkeys_cost's tracer: per pair =
  (count for ``--steps`` pairs - count for 0 pairs) / ``--steps``: what
  the allocators do now and then (jemalloc's thread-cache garbage
  collection, its decay) is in it at its average over those pairs. User
  mode only: the kernel's work (mmap, munmap, page faults) is not in it,
  so the 256 KiB glibc rows count the guard's share of a pair whose time
  is mostly the kernel's. Every step's address is kept, so the same difference per address, put to its
  function and line (addr2line on the guard's debug information), says
  where B's extra instructions are.
* Time: ``--n`` interleaved pairs. Each pair is, per allocator, a fresh A
  worker and a fresh B worker back to back, which goes first alternating
  (A, B, then B, A ...) from allocator to allocator and from pair to pair;
  each worker runs ``--repeat`` loops of each size, its figure the median.
  Per pair the ratio B / A; per measure the median of the ratios and its
  95% interval (the sign test's, figures.median_interval). On one CPU
  (``--cpu``, by default the last this process may use), as pkeys_cost.
* Verdict against <= +2%: instructions, B / A; time, met if the whole
  interval is at or below +2%, missed if all of it is above, undecided
  otherwise.
"""

from __future__ import annotations

import bisect
import collections
import importlib.abc
import importlib.util
import json
import os
import re
import statistics
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

from cloneguard.harness.process import REPO_ROOT, stop_group

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import median_interval, pct
from .goals import Goal, goal_median_ratio
from .results import Result, Table, summary_row
from .stepping import step_calls

NAME = "accounting_cost"
TITLE = "Allocator guard: what its memory accounting costs (A without, B with)"
GOAL_PCT = 2.0
LIMIT = 1.0 + GOAL_PCT / 100.0
ALLOCATORS = ("glibc", "jemalloc")
SIZES = (64, 4096, 256 * 1024)
# Pairs per timed loop, by size: ~0.1 s a loop here.
LOOP_PAIRS = {64: 2_000_000, 4096: 1_000_000, 256 * 1024: 40_000}
# The shorter of the two single-stepped calls: 0 pairs, the call's own
# instructions alone. (Not 100 as pkeys_cost: jemalloc's thread-cache
# garbage collection and decay run every so many events, thousands of
# instructions each, and a short call that holds one more or one fewer
# than its share moves the difference by tens per pair.)
STEP_BASE = 0
WARM = 10_000  # pairs of each size before anything is measured
# jemalloc's decay is driven by the clock: stepped, a pair takes some
# 10,000 times as long, and dirty pages its loop would reuse for seconds
# at full speed are purged (madvise, thousands of instructions) again and
# again, more or fewer in one run than the next. Stepped workers run
# without it (both sides); timed ones as they are.
STEP_MALLOC_CONF = "dirty_decay_ms:-1,muzzy_decay_ms:-1"
# The guard's functions that do the accounting (allocguard.c "Memory in
# use, per slot, and budgets", bigblocks.c), inlined or not.
ACCOUNTING = {
    "count",
    "count_got",
    "count_freed",
    "block_bytes",
    "glibc_mmapped",
    "within_budget",
    "block_within_budget",
    "bytes_for",
    "cga_within_budget",
    "slot_bytes",
    "over_budget",
    "bb_put",
    "bb_take",
}
GUARD_SO = f"_allocguard{sysconfig.get_config_var('EXT_SUFFIX')}"


def size_name(size: int) -> str:
    return f"{size // 1024} KiB" if size >= 1024 else f"{size} B"


def measure_name(alloc: str, size: int) -> str:
    return f"{alloc}, malloc/free {size_name(size)}"


# -- the trees ---------------------------------------------------------------
def guard_path(tree: Path) -> Path:
    return Path(tree) / "container" / "isolated" / GUARD_SO


def describe_tree(tree: Path) -> dict:
    """The tree's commit, whether its sources differ from it, and whether its
    guard counts memory (exports cga_slot_memory)."""
    tree = Path(tree).resolve()
    so = guard_path(tree)
    if not so.exists():
        raise SystemExit(f"{tree}: no built guard ({so}); build it: cd {tree} && python setup.py build_ext --inplace")

    def git(*args: str) -> str:
        p = subprocess.run(["git", "-C", str(tree), *args], capture_output=True, text=True)
        return p.stdout.strip() if p.returncode == 0 else "?"

    syms = subprocess.run(["nm", "-D", "--defined-only", str(so)], capture_output=True, text=True).stdout
    return {
        "path": str(tree),
        "commit": git("rev-parse", "HEAD"),
        "subject": git("log", "-1", "--format=%s")[:80],
        "dirty": bool(git("status", "--porcelain", "--untracked-files=no", "--", "container")),
        "guard": str(so),
        "counts_memory": " cga_slot_memory\n" in syms,
    }


class _TreeFinder(importlib.abc.MetaPathFinder):
    """cloneguard.container from TREE/container (its submodules follow its
    __path__), ahead of the editable install's mapping."""

    def __init__(self, tree: Path):
        self.pkg = Path(tree) / "container"

    def find_spec(self, fullname, path=None, target=None):
        if fullname != "cloneguard.container":
            return None
        return importlib.util.spec_from_file_location(
            fullname, self.pkg / "__init__.py", submodule_search_locations=[str(self.pkg)]
        )


# -- the worker ----------------------------------------------------------------
def _worker(tree: str, spec: dict) -> int:
    """In a process of its own, the side's guard (and jemalloc) preloaded.
    ``time``: ns per malloc/free pair, by size, ``repeat`` loops each, in a
    node process. ``step``: prints the node process's pid and the entry of
    hammer_pairs, warms up, waits for a byte on stdin (the tracer has
    attached), then calls hammer_pairs(size, N1) and (size, N2) for each
    size through a function pointer."""
    if "cloneguard.container" in sys.modules:
        raise SystemExit("cloneguard.container was imported before the tree was chosen")
    sys.meta_path.insert(0, _TreeFinder(Path(tree)))
    from cloneguard.container import allocator

    if Path(allocator.GUARD_PATH).resolve() != guard_path(Path(tree)).resolve():
        raise SystemExit(f"the guard imported is {allocator.GUARD_PATH}, not {tree}'s")
    allocator.glibc_arena_per_task()  # as the container does: M_MMAP_THRESHOLD fixed at 128 KiB
    from cloneguard.container.isolated.core import CloneCore
    from cloneguard.faults._hammer import ffi, lib

    # (core.allocator() names the malloc that malloc resolves to: the guard's, "glibc")
    out: dict = {"backend": "jemalloc" if allocator.jemalloc_active() else "glibc", "guard": allocator.GUARD_PATH}
    with CloneCore(alloc_guard=True) as core:
        if spec["kind"] == "time":

            def loops() -> None:
                for size in SIZES:
                    lib.hammer_pairs(size, WARM)
                for _ in range(spec["repeat"]):
                    for size in SIZES:
                        n = spec["pairs"][str(size)]
                        out.setdefault(str(size), []).append(lib.hammer_pairs(size, n) / n)

            child = core.spawn(loops)
        else:
            fn = ffi.cast("int64_t(*)(size_t, long)", ffi.addressof(lib, "hammer_pairs"))

            def stepped() -> None:
                for size in SIZES:
                    lib.hammer_pairs(size, WARM)  # thread caches, the guard's caller cache
                os.read(0, 1)
                for size in SIZES:
                    for n in spec["n"]:
                        fn(size, n)

            child = core.spawn(stepped)
            print(json.dumps({"pid": child.pid, "entry": int(ffi.cast("uintptr_t", fn))}), flush=True)
        death = core.wait(child, 1800)
        if death is None or death.exit_code != 0:
            raise SystemExit(f"the node process ended with {death}")
        core.release(child)
    print(json.dumps(out), flush=True)
    return 0


def _env(tree: Path, alloc: str, stepped: bool) -> dict:
    from cloneguard.container import allocator  # this checkout's: where jemalloc is

    env = dict(os.environ)
    if stepped and alloc == "jemalloc":
        env["MALLOC_CONF"] = ",".join(filter(None, [env.get("MALLOC_CONF"), STEP_MALLOC_CONF]))
    jemalloc = [allocator.jemalloc_path() or ""] if alloc == "jemalloc" else []
    env["LD_PRELOAD"] = " ".join([str(guard_path(tree)), *jemalloc])
    env.pop("CLONEGUARD_PKEYS", None)  # keys off on both sides
    return env


def _start(tree: Path, alloc: str, spec: dict, stdin=subprocess.DEVNULL) -> subprocess.Popen:
    """A worker of ``tree`` under ``alloc``."""
    return subprocess.Popen(
        [sys.executable, "-m", f"cloneguard.bench.{NAME}", "--worker", str(tree), json.dumps(spec)],
        cwd=REPO_ROOT,
        env=_env(tree, alloc, spec["kind"] == "step"),
        stdin=stdin,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        start_new_session=True,
    )


def _finish(proc: subprocess.Popen, what: str, timeout: float) -> dict:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        stop_group(proc, proc.pid, 1.0)
        raise RuntimeError(f"{what}: no answer within {timeout:g} s") from None
    stop_group(proc, proc.pid, 1.0)
    if proc.returncode != 0:
        raise RuntimeError(f"{what} exited with {proc.returncode}:\n{err.decode(errors='replace')[-3000:]}")
    return json.loads(out.decode().strip().splitlines()[-1])


def _check_backend(got: dict, alloc: str, what: str) -> None:
    if got["backend"] != alloc:
        raise RuntimeError(f"{what}: the node process allocated with {got['backend']}, not {alloc}")


def time_worker(tree: Path, alloc: str, repeat: int, pairs: dict[int, int]) -> dict:
    spec = {"kind": "time", "repeat": repeat, "pairs": {str(s): n for s, n in pairs.items()}}
    got = _finish(_start(tree, alloc, spec), f"time worker ({alloc}, {tree})", 1800)
    _check_backend(got, alloc, f"time worker ({alloc}, {tree})")
    return got


# -- instructions ------------------------------------------------------------
def _maps(pid: int) -> list[tuple[int, int, int, str]]:
    """Executable file mappings: (start, end, file offset, path)."""
    out = []
    with open(f"/proc/{pid}/maps") as f:
        for line in f:
            parts = line.split(None, 5)
            if len(parts) == 6 and "x" in parts[1] and parts[5].startswith("/"):
                lo, hi = (int(x, 16) for x in parts[0].split("-"))
                out.append((lo, hi, int(parts[2], 16), parts[5].strip()))
    return sorted(out)


def step_worker(tree: Path, alloc: str, steps: int, max_steps: int = 50_000_000) -> dict:
    """Instructions per malloc/free pair by size, single-stepped; and, per
    size, the per-pair difference by address (where they are)."""
    n1, n2 = STEP_BASE, STEP_BASE + steps
    what = f"step worker ({alloc}, {tree})"
    proc = _start(tree, alloc, {"kind": "step", "n": [n1, n2]}, stdin=subprocess.PIPE)
    maps: list[tuple[int, int, int, str]] = []
    try:
        counts, hists = step_calls(
            proc,
            what,
            2 * len(SIZES),
            max_steps=max_steps,
            histogram=True,
            on_hello=lambda hello: maps.extend(_maps(hello["pid"])),
        )
        done = _finish(proc, what, 120)
    except BaseException:
        stop_group(proc, proc.pid, 1.0)
        raise
    _check_backend(done, alloc, what)
    per_op, where = {}, {}
    for i, size in enumerate(SIZES):
        per_op[str(size)] = (counts[2 * i + 1] - counts[2 * i]) / steps
        diff = hists[2 * i + 1].copy()
        diff.subtract(hists[2 * i])
        where[str(size)] = _symbolize({a: c / steps for a, c in diff.items() if c}, maps)
    return {"per_op": per_op, "counts": counts, "n": [n1, n2], "where": where}


def _symbolize(per_addr: dict[int, float], maps: list[tuple[int, int, int, str]]) -> list[dict]:
    """Instructions per pair by place: in the guard by function (its inline
    chain, innermost first) and line, elsewhere by object."""
    starts = [m[0] for m in maps]
    places: dict[tuple, float] = collections.defaultdict(float)
    guard: dict[str, list[tuple[int, float]]] = collections.defaultdict(list)
    for addr, c in per_addr.items():
        i = bisect.bisect_right(starts, addr) - 1
        if i < 0 or addr >= maps[i][1]:
            places[("?", "", "")] += c
            continue
        lo, _, off, path = maps[i]
        if path.endswith(GUARD_SO):
            guard[path].append((addr - lo + off, c))
        else:
            places[(Path(path).name, _dynsym(path, addr - lo + off), "")] += c
    for path, items in guard.items():
        for (_, c), chain in zip(items, _addr2line(path, [o for o, _ in items]), strict=True):
            places[(Path(path).name, " < ".join(f for f, _ in chain), chain[0][1] if chain else "?")] += c
    return [
        {"object": o, "function": f, "line": ln, "per_pair": round(c, 3)}
        for (o, f, ln), c in sorted(places.items(), key=lambda kv: -abs(kv[1]))
    ]


_DYNSYMS: dict[str, tuple[list[int], list[tuple[int, str]]]] = {}


def _dynsym(path: str, off: int) -> str:
    """The exported function of ``path`` whose bytes hold offset ``off``
    (nm -D -S), "" if none (an internal one)."""
    if path not in _DYNSYMS:
        p = subprocess.run(["nm", "-D", "-S", "--defined-only", path], capture_output=True, text=True)
        syms = sorted(
            (int(f[0], 16), (int(f[0], 16) + int(f[1], 16), f[3]))
            for f in (line.split() for line in p.stdout.splitlines())
            if len(f) == 4 and f[2] in "TtWi"
        )
        _DYNSYMS[path] = ([a for a, _ in syms], [e for _, e in syms])
    starts, ends = _DYNSYMS[path]
    i = bisect.bisect_right(starts, off) - 1
    return ends[i][1] if i >= 0 and off < ends[i][0] else ""


def _addr2line(path: str, offsets: list[int]) -> list[list[tuple[str, str]]]:
    """Per offset its inline chain [(function, file:line)], innermost first."""
    if not offsets:
        return []
    p = subprocess.run(
        ["addr2line", "-a", "-f", "-i", "-e", path, *[hex(o) for o in offsets]], capture_output=True, text=True
    )
    chains: list[list[tuple[str, str]]] = []
    lines = p.stdout.splitlines()
    k = 0
    while k < len(lines):
        if lines[k].startswith("0x"):
            chains.append([])
            k += 1
            continue
        func, where = lines[k], lines[k + 1] if k + 1 < len(lines) else "?"
        where = re.sub(r" \(discriminator \d+\)$", "", where)
        chains[-1].append((func, f"{Path(where.split(':')[0]).name}:{where.rsplit(':', 1)[-1]}"))
        k += 2
    if len(chains) != len(offsets):
        return [[] for _ in offsets]
    return chains


def accounting_fn(row: dict) -> str | None:
    """The outermost accounting function in a guard line's inline chain
    (what malloc or free called), or None."""
    if not row["line"]:
        return None
    chain = [f for f in row["function"].split(" < ") if f in ACCOUNTING]
    return chain[-1] if chain else None


def accounting_share(where: list[dict]) -> float:
    """Instructions per pair on the guard's lines whose inline chain passes
    through an accounting function."""
    return sum(r["per_pair"] for r in where if accounting_fn(r))


def guard_share(where: list[dict]) -> float:
    return sum(r["per_pair"] for r in where if r["object"] == GUARD_SO)


def function_share(where: list[dict], function: str) -> float:
    """Instructions per pair in an exported function of a library (not the guard)."""
    return sum(r["per_pair"] for r in where if r["function"] == function and not r["line"])


# -- the pairs ---------------------------------------------------------------
def measure_time(trees: dict[str, Path], n: int, repeat: int, pairs: dict[int, int], cpu: int | None) -> list[dict]:
    """Per pair, per allocator: the order, and each side's loops (ns per pair, by size)."""
    saved = os.sched_getaffinity(0)
    if cpu is not None:
        os.sched_setaffinity(0, {cpu})  # the workers inherit it
    out = []
    try:
        for i in range(n):
            t0 = time.monotonic()
            rec: dict = {}
            for k, alloc in enumerate(ALLOCATORS):
                order = ("A", "B") if (i + k) % 2 == 0 else ("B", "A")
                got = {side: time_worker(trees[side], alloc, repeat, pairs) for side in order}
                rec[alloc] = {"first": order[0], **{side: {str(s): got[side][str(s)] for s in SIZES} for side in "AB"}}
            rec["seconds"] = round(time.monotonic() - t0, 2)
            out.append(rec)
    finally:
        os.sched_setaffinity(0, saved)
    return out


def ratios(pairs: list[dict], alloc: str, size: int) -> tuple[list[float], list[float], list[float]]:
    """A's and B's figure per pair (the median of its loops) and B / A."""
    a = [statistics.median(p[alloc]["A"][str(size)]) for p in pairs]
    b = [statistics.median(p[alloc]["B"][str(size)]) for p in pairs]
    return a, b, [y / x for x, y in zip(a, b, strict=True)]


def judge_time(measure: str, rs: list[float]) -> Goal:
    return goal_median_ratio(f"≤ +{GOAL_PCT:g}% time with the accounting (95% interval of B ÷ A)", measure, rs, LIMIT)


def judge_instructions(measure: str, a: float, b: float) -> Goal:
    goal = f"≤ +{GOAL_PCT:g}% instructions with the accounting (B ÷ A)"
    r = b / a
    shown = f"{a:.1f} → {b:.1f} ({pct(r)})"
    return Goal(goal, measure, shown, r <= LIMIT, "met" if r <= LIMIT else f"missed: {pct(r)}, the goal +{GOAL_PCT:g}%")


def _count_instructions(trees: dict[str, Path], steps: int) -> tuple[dict[str, dict[str, dict]], str | None]:
    """Each side's instructions per pair, single-stepped; and why not, where ptrace is refused."""
    instr: dict[str, dict[str, dict]] = {}
    uncounted = None  # why the instructions were not counted
    if steps > 0:
        try:
            for alloc in ALLOCATORS:
                instr[alloc] = {side: step_worker(trees[side], alloc, steps) for side in "AB"}
        except OSError as exc:  # ptrace refused (Yama, a seccomp filter, no CAP_SYS_PTRACE ...)
            instr, uncounted = {}, str(exc)
    return instr, uncounted


def _instructions_table(instr: dict, steps: int, goals: list[Goal], summary: list[dict]) -> Table:
    """Instructions per pair, A and B (goals and summary rows appended)."""
    t_instr = Table(
        f"Instructions per malloc/free pair in a node process (single-stepped, {steps} pairs)",
        ["measure", "A", "B", "B − A", "B ÷ A", "B: on accounting lines", "verdict (≤ +2%)"],
    )
    for alloc in instr:
        for size in SIZES:
            m = measure_name(alloc, size)
            ia, ib = instr[alloc]["A"]["per_op"][str(size)], instr[alloc]["B"]["per_op"][str(size)]
            where_b = instr[alloc]["B"]["where"][str(size)]
            acc = accounting_share(where_b)
            sal = function_share(where_b, "sallocx") - function_share(instr[alloc]["A"]["where"][str(size)], "sallocx")
            extra = f"{acc:.1f}" + (f" + sallocx {sal:+.1f}" if alloc == "jemalloc" else "")
            goal = judge_instructions(m + " (instructions)", ia, ib)
            goals.append(goal)
            t_instr.add(m, f"{ia:.1f}", f"{ib:.1f}", f"{ib - ia:+.1f}", pct(ib / ia), extra, goal.verdict)
            summary.append(summary_row(NAME, m + " (instructions)", "A vs B", None, median=goal.measured,
                                       goal=goal.goal, verdict=goal.verdict))  # fmt: skip
    return t_instr


def _time_table(pair_data: list[dict], n: int, goals: list[Goal], summary: list[dict]) -> Table:
    """Time per pair, B ÷ A in interleaved pairs (goals and summary rows appended)."""
    t_time = Table(
        f"Time per malloc/free pair in a node process: {n} interleaved pairs of workers",
        ["measure", "pairs", "A: median (ns)", "B: median (ns)", "B ÷ A: median of the ratios", "95% interval",
         "verdict (≤ +2%)"],
    )  # fmt: skip
    for alloc in ALLOCATORS:
        for size in SIZES:
            m = measure_name(alloc, size)
            xa, xb, rs = ratios(pair_data, alloc, size)
            goal = judge_time(m + " (time)", rs)
            goals.append(goal)
            ci = median_interval(rs) if rs else None
            t_time.add(
                m,
                len(rs),
                f"{statistics.median(xa):.1f}" if xa else "–",
                f"{statistics.median(xb):.1f}" if xb else "–",
                pct(statistics.median(rs)) if rs else "–",
                f"{pct(ci[0])} … {pct(ci[1])} ({100 * ci[2]:.1f}%)" if ci else "– (fewer than 6 pairs)",
                goal.verdict,
            )
            summary.append(summary_row(NAME, m + " (time)", "A vs B", None, median=goal.measured, goal=goal.goal,
                                       verdict=goal.verdict))  # fmt: skip
    return t_time


def _where_table(instr: dict) -> Table:
    """Where B's extra instructions are."""
    groups = ["block_within_budget", "count_got", "count_freed", "bb_put", "bb_take"]
    t_where = Table(
        "Where B's extra instructions are, per pair: B's on the accounting functions (each with what is "
        "inlined into it), jemalloc's sallocx (B − A), the rest of the guard (B − A less those) and "
        "everything else (B − A)",
        ["measure", "B − A", *groups, "other accounting", "sallocx", "rest of the guard", "elsewhere"],
    )
    for alloc in instr:
        for size in SIZES:
            wa, wb = instr[alloc]["A"]["where"][str(size)], instr[alloc]["B"]["where"][str(size)]
            by_fn: dict[str, float] = collections.defaultdict(float)
            for r in wb:
                fn = accounting_fn(r)
                if fn:
                    by_fn[fn if fn in groups else "other"] += r["per_pair"]
            sal = function_share(wb, "sallocx") - function_share(wa, "sallocx")
            d_guard = guard_share(wb) - guard_share(wa)
            d_all = instr[alloc]["B"]["per_op"][str(size)] - instr[alloc]["A"]["per_op"][str(size)]
            t_where.add(
                measure_name(alloc, size),
                f"{d_all:+.1f}",
                *[f"{by_fn[g]:.1f}" for g in [*groups, "other"]],
                f"{sal:+.1f}",
                f"{d_guard - sum(by_fn.values()):+.1f}",
                f"{d_all - d_guard - sal:+.1f}",
            )
    return t_where


def _side(info: dict, s: str) -> str:
    d = info[s]
    return (
        f"{s}: {d['path']} at {d['commit'][:10]} ({d['subject']})"
        + (", with uncommitted changes under container/" if d["dirty"] else "")
        + f"; its guard {'counts' if d['counts_memory'] else 'does not count'} memory"
        " (cga_slot_memory exported or not)"
    )


def _notes(
    info: dict, n: int, repeat: int, steps: int, loop_pairs: dict, pin: int | None, seconds: dict, uncounted: str | None
) -> list[str]:
    """How it was measured, and on which trees."""
    return [
        _side(info, "A") + ".",
        _side(info, "B") + ".",
        "Each worker: a fresh process, its side's guard preloaded (then jemalloc for the jemalloc rows) and its "
        "side's cloneguard.container (clone core and guard built together); a CloneCore with the guard on "
        "spawns one node process, which runs faults/hammer.c's hammer_pairs(size, n) (n × free(malloc(size)), "
        f"in C) after {WARM} warm-up pairs of each size. Protection keys off on both sides.",
        f"Instructions: bench.stepping's ptrace stepper, per pair (count for {STEP_BASE + steps} pairs − count for "
        f"{STEP_BASE}: the call itself) / {steps}, jemalloc's occasional work (thread-cache GC, decay) at its "
        "average over them; user mode only (not the kernel's mmap, munmap, page faults); a rep-prefixed instruction "
        "counts once per iteration. 'B: on accounting lines': "
        "B's instructions per pair at addresses whose inline chain (addr2line) passes through "
        + ", ".join(sorted(ACCOUNTING))
        + "; under jemalloc, plus the change in instructions inside jemalloc's sallocx (B − A), which "
        "block_bytes calls on every malloc and free. Stepped jemalloc workers run with MALLOC_CONF="
        f"{STEP_MALLOC_CONF} (both sides): its decay runs by the clock, and stepping is ~10,000 times slower.",
        f"Time: {n} pairs; per pair and allocator a fresh A and a fresh B worker back to back, the first "
        f"alternating; each {repeat} loops of {', '.join(f'{loop_pairs[s]} × {size_name(s)}' for s in SIZES)}, "
        "its figure the median; B ÷ A per pair, the median of the ratios with the sign test's 95% interval "
        "(exact coverage in brackets). "
        + (f"All on CPU {pin}." if pin is not None else "On any CPU.")
        + f" Stepping took {seconds['instructions']:.0f} s, the pairs {seconds['time']:.0f} s.",
        *([f"Instructions not counted: {uncounted}."] if uncounted else []),
    ]


def run(
    *,
    a: Path,
    b: Path = REPO_ROOT,
    n: int = 20,
    repeat: int = 5,
    steps: int = 1000,
    pairs_scale: float = 1.0,
    cpu: int | None = None,
    out=DEFAULT_OUT,
    quiet: bool = False,
) -> Result:
    trees = {"A": Path(a).resolve(), "B": Path(b).resolve()}
    info = {side: describe_tree(t) for side, t in trees.items()}
    if cpu is None:
        cpu = max(os.sched_getaffinity(0))
    pin = cpu if cpu >= 0 else None
    loop_pairs = {s: max(1, int(k * pairs_scale)) for s, k in LOOP_PAIRS.items()}
    args = {"a": str(trees["A"]), "b": str(trees["B"]), "n": n, "repeat": repeat, "steps": steps, "cpu": cpu}
    if pairs_scale != 1.0:
        args["pairs_scale"] = pairs_scale
    t0 = time.monotonic()
    instr, uncounted = _count_instructions(trees, steps)
    t1 = time.monotonic()
    pair_data = measure_time(trees, n, repeat, loop_pairs, pin)
    seconds = {"instructions": round(t1 - t0, 1), "time": round(time.monotonic() - t1, 1)}

    goals: list[Goal] = []
    summary: list[dict] = []
    tables = [_instructions_table(instr, steps, goals, summary), _time_table(pair_data, n, goals, summary)]
    if instr:
        tables.append(_where_table(instr))
    notes = _notes(info, n, repeat, steps, loop_pairs, pin, seconds, uncounted)
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, args),
        args | {"out": str(out)},
        tables,
        goals,
        notes,
        summary,
        {
            "trees": info,
            "instructions": instr,
            "not_counted": uncounted,
            "pairs": pair_data,
            "loop_pairs": loop_pairs,
            "seconds": seconds,
        },
        [],
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        return _worker(argv[1], json.loads(argv[2]))
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--a", type=Path, required=True, help="tree A (without the accounting), built in place")
    parser.add_argument("--b", type=Path, default=REPO_ROOT, help="tree B (with it; default: this checkout)")
    parser.add_argument("--n", type=int, default=20, help="interleaved A/B pairs (default: %(default)s)")
    parser.add_argument("--repeat", type=int, default=5, help="timed loops per size and worker (default: %(default)s)")
    parser.add_argument(
        "--steps", type=int, default=1000, help="malloc/free pairs single-stepped, 0: none (default: %(default)s)"
    )
    parser.add_argument(
        "--pairs-scale", type=float, default=1.0, help="scale the timed loops' lengths (default: %(default)s)"
    )
    parser.add_argument(
        "--cpu", type=int, default=None, help="run on this CPU alone, -1: on any (default: the last one usable)"
    )
    opts = parser.parse_args(argv)
    run(
        a=opts.a,
        b=opts.b,
        n=opts.n,
        repeat=opts.repeat,
        steps=opts.steps,
        pairs_scale=opts.pairs_scale,
        cpu=opts.cpu,
        out=opts.out,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
