"""The memory watch's margin: how far past its trigger a fast leak gets.

    python -m cloneguard.bench.memory_watch                  # 0.25, 1, 2, 4, 8 GiB/s, 5 trials each, 1 GiB
    python -m cloneguard.bench.memory_watch --rates 2 --trials 20 --limit 2G --margin 32M
    python -m cloneguard.bench.memory_watch --rates 2 8 --cpu-load 4      # every CPU busy beside it

Each trial is a fresh ``component_container --isolated`` in a memory cgroup
the benchmark makes with ``--limit`` (harness/memory_cgroup.py; never a
leak without one: where none can be made, nothing runs and the report says
why), with a demo_robot::Odometry (50 Hz) and a faults::MemoryLeak that,
``--delay`` s after its construction, keeps ``step`` = rate x ``--period``
bytes every ``--period`` s (``--kind``: ``native`` malloc + memset,
``bytes`` a bytearray, ``python`` small objects) until it is ended. Its
``~/held`` messages give the rate it achieved; a rate it cannot reach makes
it leak back to back, as fast as it can.

Per trial: whether the watch ended the leak (its CRASHED text, ``out of
memory: the container used N MiB``), N against the trigger (the limit less
the margin, as the container logged it), the overshoot N - trigger, the use
after the end (the cgroup's usage less its inactive file cache, as the watch
counts it, 0.5 s after the CRASHED), the cgroup's peak (v1
``memory.max_usage_in_bytes``, v2 ``memory.peak``) against the limit, the
kernel's OOM kills in the cgroup, whether the container lived on (it answers
ListNodes), and the leak's start -> CRASHED at the client.

The margin a rate needs is at least the largest overshoot seen at it (N, or
the use after the end where that is higher, less the trigger), with the
number of trials it was seen in; a trial the watch lost (the kernel acted)
says only that the margin was too small.

``--cpu-load N`` keeps N processes of the benchmark's own spinning through
each trial: every CPU busy, as under a full CI load, which the watch's
thread (the monitor's, an ordinary one) and the leak share with them.
"""

from __future__ import annotations

import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

from cloneguard_interfaces.msg import ComponentEvent
from std_msgs.msg import UInt64

from cloneguard.container.isolated.memory_watch import MIN_MARGIN, MemoryLimit
from cloneguard.container.memory_budget import parse_size
from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness import procfs
from cloneguard.harness.client import HarnessTimeout
from cloneguard.harness.factory import ContainerFactory
from cloneguard.harness.memory_cgroup import MemoryCgroup, MemoryCgroupUnavailable
from cloneguard.harness.system import NodeSpec, System

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .loads import event_received
from .results import Result, Table, summary_row
from .session import Session

NAME = "memory_watch"
TITLE = "Memory watch: the margin a leak needs"
MiB, GiB = 1 << 20, 1 << 30
RATES = [0.25, 1.0, 2.0, 4.0, 8.0]  # GiB/s asked
CONTAINER_ARGS = ["--isolated"]
ODOMETRY = NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 50.0})
LEAK = "/leak"
SPIN = "while True: pass"  # --cpu-load's processes
AFTER_END_S = 0.5  # CRASHED -> the cgroup read: the node's end and the watch's reap
ENDED = re.compile(r"out of memory: the container used (?P<used>[\d.]+) MiB of the (?P<limit>[\d.]+) MiB")
TRIGGER_LOGGED = re.compile(r"memory watch: the container may use ([\d.]+) MiB .*; from ([\d.]+) MiB on")


def _cgroup_use(cgroup: MemoryCgroup) -> int:
    """Its usage less its inactive file cache: what the watch counts."""
    key = "total_inactive_file" if cgroup.kind == "v1" else "inactive_file"
    stat = dict(line.split() for line in (cgroup.dir / "memory.stat").read_text().splitlines())
    return cgroup.usage() - int(stat.get(key, 0))


def _cgroup_peak(cgroup: MemoryCgroup) -> int | None:
    name = "memory.max_usage_in_bytes" if cgroup.kind == "v1" else "memory.peak"
    try:
        return int((cgroup.dir / name).read_text())
    except OSError:  # cgroup2 before Linux 5.19 has no memory.peak
        return None


def _wait_end(robot: System, timeout: float):
    """The leak's CRASHED as the client got it, or None once the container is
    gone (the kernel's OOM killer ends every process of its address space)."""
    uid = robot.node(LEAK).unique_id
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            return event_received(robot.client, ComponentEvent.CRASHED, uid, 0.25)
        except HarnessTimeout:
            if not robot.alive():
                return None
    raise HarnessTimeout(f"the leak was neither ended nor did the container die within {timeout:.0f} s")


def _achieved(held) -> tuple[float | None, int | None]:
    """Bytes/s between the first and last ~/held message received, and when
    the leak began (client clock: the first message, less its bytes at that rate)."""
    items = held.items()
    if len(items) < 2 or items[-1].at_ns <= items[0].at_ns:
        return None, None
    first, last = items[0], items[-1]
    rate = (last.msg.data - first.msg.data) / ((last.at_ns - first.at_ns) / 1e9)
    if rate <= 0:
        return None, None
    return rate, first.at_ns - int(first.msg.data / rate * 1e9)


def trial(
    session: Session,
    n: int,
    *,
    limit: int,
    margin: str | None,
    kind: str,
    rate: float,
    period: float,
    delay: float,
    cpu_load: int = 0,
) -> tuple[dict, list[str]]:
    """One fresh container, one leak at ``rate`` GiB/s, ``cpu_load``
    spinning processes beside it: what happened, and what it left behind
    (nothing, if all went well)."""
    step = max(4096, round(rate * GiB * period))
    leak = NodeSpec(
        TESTRIG,
        "faults::MemoryLeak",
        name="leak",
        parameters={"kind": kind, "step": step, "period": period, "delay": delay},
    )
    args = CONTAINER_ARGS + (["--memory-margin", margin] if margin is not None else [])
    lease = session.lease()
    factory = ContainerFactory(lease.domain_id, session.log_dir / f"trial-{n:03d}")
    out: dict = {"rate_asked": rate, "step": step}
    spinners = [subprocess.Popen([sys.executable, "-c", SPIN], start_new_session=True) for _ in range(cpu_load)]
    try:
        robot = System(factory, [ODOMETRY, leak], args, memory_limit=limit)
        cgroup = robot.proc.memory_cgroup
        assert cgroup is not None
        held = robot.topic(UInt64, f"{LEAK}/held")
        out["use_before"] = _cgroup_use(cgroup)
        logged = robot.proc.wait_for_log(TRIGGER_LOGGED.pattern, 10)
        out["limit_seen"], out["trigger"] = (round(float(g) * MiB) for g in logged.groups())
        ended = _wait_end(robot, timeout=30 + delay + 2 * limit / (rate * GiB))
        if ended is not None:
            time.sleep(AFTER_END_S)
        said = ENDED.search(ended.msg.error_message) if ended is not None else None
        out["ended_by_watch"] = said is not None
        out["crashed_text"] = ended.msg.error_message if ended is not None else None
        out["watch_used"] = round(float(said["used"]) * MiB) if said else None
        out["oom_kills"] = cgroup.oom_kills()
        out["peak"] = _cgroup_peak(cgroup)
        out["use_after"] = _cgroup_use(cgroup) if robot.alive() else None
        out["rate"], start = _achieved(held)
        out["held_last"] = held.messages()[-1].data if len(held) else None
        out["start_to_crashed_s"] = (ended.at_ns - start) / 1e9 if ended is not None and start else None
        try:
            robot.client.list(timeout=5)
            out["survived"] = robot.alive()
        except (AssertionError, HarnessTimeout):
            out["survived"] = False
        out["others_ended"] = [
            e.full_node_name
            for e in robot.client.events.messages()
            if e.event_type == ComponentEvent.CRASHED and e.full_node_name != LEAK
        ]
    finally:
        for spinner in spinners:
            spinner.kill()
            spinner.wait()
        started = list(factory.started)
        factory.stop_all()
        session.release(lease)
    left = [f"processes left in group {p.pgid}" for p in started if not procfs.wait_group_empty(p.pgid, timeout=2.0)]
    left += [f"cgroup left: {p.memory_cgroup.dir}" for p in started if p.memory_cgroup and p.memory_cgroup.dir.exists()]
    return out, left


def _mib(x: float | None, sign: bool = False) -> str:
    return "–" if x is None else f"{x / MiB:+.1f}" if sign else f"{x / MiB:.1f}"


def _med_max(values: list, fmt) -> str:
    vals = [v for v in values if v is not None]
    return "–" if not vals else f"{fmt(statistics.median(vals))} / {fmt(max(vals))}"


def overshoot(t: dict) -> int | None:
    """How far past the trigger the use got before the leak's end: the
    watch's reading, or the use after the end where that is higher."""
    if not t.get("ended_by_watch"):
        return None
    return max(t["watch_used"], t["use_after"] or 0) - t["trigger"]


def run(
    *,
    rates: list[float] = RATES,
    trials: int = 5,
    limit: str = "1G",
    margin: str | None = None,
    kind: str = "native",
    period: float = 0.01,
    delay: float = 2.0,
    cpu_load: int = 0,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
) -> Result:
    params = {"rates": list(rates), "trials": trials, "limit": limit, "kind": kind, "period": period, "delay": delay}
    if margin is not None:
        params["margin"] = margin
    if cpu_load:
        params["cpu_load"] = cpu_load
    limit_b = parse_size(limit)
    margin_b = MemoryLimit(limit_b, "", "").margin(parse_size(margin) if margin is not None else None)
    by_rate: dict[float, list[dict]] = {r: [] for r in rates}
    problems: list[str] = []
    why = None
    session = Session(NAME, keep_logs=keep_logs)
    try:
        n = 0
        for _ in range(trials):
            for r in rates:  # interleaved: a slow spell of the machine hits every rate
                n += 1
                t, left = trial(
                    session,
                    n,
                    limit=limit_b,
                    margin=margin,
                    kind=kind,
                    rate=r,
                    period=period,
                    delay=delay,
                    cpu_load=cpu_load,
                )
                by_rate[r].append(t)
                problems += left
    except MemoryCgroupUnavailable as exc:
        why = str(exc)
    finally:
        problems += session.close()

    table = Table(
        f"Per rate: median / max over the trials (MiB; limit {_mib(limit_b)} MiB, margin {_mib(margin_b)} MiB, "
        f"trigger {_mib(limit_b - margin_b)} MiB)",
        [
            "leak asked (GiB/s)",
            "achieved (GiB/s)",
            "trials",
            "ended by the watch",
            "kernel OOM kills",
            "container lived on",
            "use before the leak",
            "watch acted at (N)",
            "overshoot (N − trigger)",
            "use after the end",
            "cgroup peak",
            "leak start → CRASHED (ms)",
            "smallest margin that sufficed",
        ],
    )
    summary = []
    for r, ts in by_rate.items():
        if not ts:
            continue
        shoots = [s for s in map(overshoot, ts) if s is not None]  # all of them where none was lost
        lost = sum(1 for t in ts if not t["ended_by_watch"])
        needed = (
            f"{_mib(max(shoots))} MiB (n={len(ts)})"
            if not lost
            else f"> {_mib(margin_b)} MiB: the watch lost {lost} of {len(ts)}"
        )
        table.add(
            f"{r:g}",
            _med_max([t["rate"] for t in ts], lambda x: f"{x / GiB:.2f}"),
            len(ts),
            sum(t["ended_by_watch"] for t in ts),
            sum(t["oom_kills"] for t in ts),
            sum(t["survived"] for t in ts),
            _med_max([t["use_before"] for t in ts], _mib),
            _med_max([t["watch_used"] for t in ts], _mib),
            _med_max([t["watch_used"] - t["trigger"] if t["watch_used"] else None for t in ts], _mib),
            _med_max([t["use_after"] for t in ts], _mib),
            _med_max([t["peak"] for t in ts], _mib),
            _med_max([t["start_to_crashed_s"] for t in ts], lambda x: f"{x * 1e3:.0f}"),
            needed,
        )
        won = [s for s in shoots if s is not None]
        summary.append(
            summary_row(
                "memory watch",
                f"overshoot past the trigger, {r:g} GiB/s leak asked"
                + (f", {cpu_load} processes spinning" if cpu_load else ""),
                "isolated",
                {"n": len(ts)},
                median=f"{_mib(statistics.median(won))} MiB" if won else "–",
                p90=f"max {_mib(max(won))} MiB" if won else "–",
                goal=f"≤ the margin ({_mib(margin_b)} MiB)",
                verdict=f"missed: the kernel acted in {lost}" if lost else "met",
            )
        )
    per_trial = Table(
        "Every trial (MiB)",
        [
            "leak asked (GiB/s)",
            "achieved (GiB/s)",
            "ended by",
            "N",
            "N − trigger",
            "use after",
            "peak",
            "OOM kills",
            "lived on",
            "start → CRASHED (ms)",
        ],
    )
    for r, ts in by_rate.items():
        for t in ts:
            per_trial.add(
                f"{r:g}",
                "–" if t["rate"] is None else f"{t['rate'] / GiB:.2f}",
                "the watch" if t["ended_by_watch"] else "the kernel" if t["oom_kills"] else "?",
                _mib(t["watch_used"]),
                _mib(t["watch_used"] - t["trigger"] if t["watch_used"] else None, sign=True),
                _mib(t["use_after"]),
                _mib(t["peak"]),
                t["oom_kills"],
                "yes" if t["survived"] else "no",
                "–" if t["start_to_crashed_s"] is None else f"{t['start_to_crashed_s'] * 1e3:.0f}",
            )
    others = [name for ts in by_rate.values() for t in ts for name in t["others_ended"]]
    seen = {t["limit_seen"] for ts in by_rate.values() for t in ts} - {limit_b}
    notes = (
        [f"Not measured on this machine: no memory cgroup can be made ({why})."]
        if why
        else [
            f"Each trial a fresh `component_container {' '.join(CONTAINER_ARGS)}"
            + (f" --memory-margin {margin}" if margin is not None else "")
            + f"` in a memory cgroup of {_mib(limit_b)} MiB (swap held to it), with demo_robot::Odometry "
            f"(50 Hz) and faults::MemoryLeak kind={kind}, step = rate × {period:g} s every {period:g} s, "
            f"from {delay:g} s after its construction; trials interleaved over the rates."
            + (f" {cpu_load} processes of the benchmark's own spin through each trial." if cpu_load else ""),
            f"Margin: {'--memory-margin ' + margin if margin is not None else 'the default'} = "
            f"{_mib(margin_b)} MiB (default: 2% of the limit, at least {MIN_MARGIN >> 20} MiB); trigger = "
            "limit − margin, from the container's own log line. The watch looks every 1-100 ms, sleeping "
            "as long as a 4 GiB/s leak would take to use half of what is left before the trigger "
            "(memwatch.c).",
            "N: the use the watch read when it acted (its CRASHED text); use after the end: the cgroup's "
            f"usage less its inactive file cache {AFTER_END_S:g} s after the CRASHED (the dead node's memory "
            "stays in the container); peak: the cgroup's own high-water mark, file cache included (v1 "
            "memory.max_usage_in_bytes, v2 memory.peak), which the kernel holds to the limit by reclaiming "
            "cache before it kills. The smallest margin that sufficed: the largest overshoot (N, or the use "
            "after the end where higher, less the trigger) seen at that rate.",
            "Achieved rate: the leak's ~/held messages (bytes it holds) first to last, at the client; the "
            "leak's start is the first message less its bytes at that rate. A rate above what one thread "
            "can page in makes the leak run back to back: its achieved figure is then this machine's.",
        ]
        + ([f"The container found another limit than the cgroup's: {sorted(seen)} bytes."] if seen else [])
        + ([f"Other nodes ended in these trials: {others}."] if others else [])
    )
    raw = {str(r): ts for r, ts in by_rate.items()}
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, params),
        dict(params, out=str(out)),
        [table, per_trial],
        [],
        notes,
        [summary_row("memory watch", "margin", "isolated", None, verdict=f"not measured: {why}")] if why else summary,
        {"trials": raw, "limit": limit_b, "margin": margin_b, "unavailable": why},
        problems,
    )
    return finish(result, Path(out), quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--rates", nargs="+", type=float, default=RATES, help="leak rates, GiB/s")
    parser.add_argument("--trials", type=int, default=5, help="trials per rate, each a fresh container (default: 5)")
    parser.add_argument("--limit", default="1G", help="the memory cgroup's limit (default: %(default)s)")
    parser.add_argument("--margin", default=None, help="the container's --memory-margin (default: its own)")
    parser.add_argument("--kind", choices=["native", "bytes", "python"], default="native", help="what the leak keeps")
    parser.add_argument("--period", type=float, default=0.01, help="seconds between the leak's steps")
    parser.add_argument("--delay", type=float, default=2.0, help="seconds from the leak's load to its start")
    parser.add_argument("--cpu-load", type=int, default=0, help="spinning processes through each trial (default 0)")
    opts = parser.parse_args(argv)
    result = run(
        rates=opts.rates,
        trials=opts.trials,
        limit=opts.limit,
        margin=opts.margin,
        kind=opts.kind,
        period=opts.period,
        delay=opts.delay,
        cpu_load=opts.cpu_load,
        out=opts.out,
        keep_logs=opts.keep_logs,
    )
    return 1 if result.cleanup else 0


if __name__ == "__main__":
    sys.exit(main())
