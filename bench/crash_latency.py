"""Fault -> CRASHED event latency, for a node's process killed from outside.

    python -m cloneguard.bench.crash_latency                # n=100 per profile and signal
    python -m cloneguard.bench.crash_latency --n 300 --signals SIGKILL
    python -m cloneguard.bench.crash_latency --others 47       # among 47 idle nodes

One isolated container per profile (per-node, shared), with ``--others``
idle Heartbeat nodes (1 Hz) loaded first into each. Each trial loads a
cloneguard::Heartbeat, lets it run ``--settle`` s, then the benchmark takes
time.time_ns() (and CLOCK_MONOTONIC) and os.kill()s the node's process (its
pid from the LOADED event, checked to be in the container's process group)
with SIGKILL or SIGSEGV, and waits for the CRASHED event. Measured: kill ->
the event's stamp (the container's wall clock when it published it), and
kill -> the event received by the client. Trials are interleaved over
profiles and signals. A container is replaced after ``--recycle`` crashes (a
crash leaves the dead node's objects in memory by design), when a trial gets
no CRASHED within the timeout (counted as lost), or when it no longer answers
LoadNode after a crash (counted on that crash; its log tail, and with gdb what
its threads wait on, go into the JSON).

The in-container monitor's own detection time is not published (the event
has no such stamp); it is measured instead on a standalone CloneCore in a
worker process (python -m cloneguard.bench._core_worker kill): an idle child killed from
outside -> the monitor's detection stamp, and -> the Python on_event call.

Goal: median ≤ 0.8 ms (fault -> CRASHED), one node and among 47 others.
"""

from __future__ import annotations

import os
import re
import signal
import sys
import time
from typing import Any

from cloneguard_interfaces.msg import ComponentEvent

from cloneguard.harness import diagnose, procfs
from cloneguard.harness.client import HarnessTimeout
from cloneguard.harness.factory import log_tail

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ms, ms, stats
from .goals import goal_at_most
from .loads import event_received, stamp_ns, timed_load
from .modes import HEARTBEAT_PARAMS, label
from .results import Result, Table, summary_row
from .session import Session

NAME = "crash_latency"
TITLE = "Crash latency: fault → CRASHED event"
GOAL_MS = 0.8
GOAL = f"median ≤ {GOAL_MS:g} ms"
PROFILES = ["isolated-per-node", "isolated-shared"]
SIGNALS = ["SIGKILL", "SIGSEGV"]
EVENT_TIMEOUT_S = 10.0
LOAD_TIMEOUT_S = 10.0
_LOG_LINE = re.compile(r"^\[(\w+)\] \[(\d+)\.(\d+)\] \[[^\]]*\]: (.*)$")


def log_stamps(text: str) -> dict[tuple[str, int], int]:
    """From a container log: when (wall clock ns, rcutils' stamp) the host
    logged that it keeps a dead node's objects ("leak", unique_id) and when
    the manager logged the death ("died", unique_id)."""
    out: dict[tuple[str, int], int] = {}
    for line in text.splitlines():
        m = _LOG_LINE.match(line)
        if not m:
            continue
        t = int(m.group(2)) * 1_000_000_000 + int(m.group(3).ljust(9, "0")[:9])
        msg = m.group(4)
        leak = re.match(r"unique_id (\d+): the dead process", msg)
        if leak:
            out.setdefault(("leak", int(leak.group(1))), t)
        died = re.search(r"\(unique_id (\d+), pid \d+\) died:", msg)
        if died:
            out.setdefault(("died", int(died.group(1))), t)
    return out


def _load(running, i: int):
    return timed_load(running, node_name=f"victim{i}", timeout=LOAD_TIMEOUT_S)


def _crash(running, trial, sig: signal.Signals, settle: float) -> dict:
    time.sleep(settle)
    st = procfs.stat(trial.pid)
    if st is None or st.pgrp != running.proc.pgid or trial.pid == running.proc.pid:
        raise AssertionError(f"pid {trial.pid} is not a child process of the container {running.proc.pid}")
    t_wall = time.time_ns()
    t_mono = time.monotonic_ns()
    os.kill(trial.pid, sig)
    item = event_received(running.client, ComponentEvent.CRASHED, trial.unique_id, EVENT_TIMEOUT_S)
    return {
        "stamp_ns": stamp_ns(item.msg) - t_wall,
        "client_ns": item.at_ns - t_mono,
        "exit_signal": item.msg.exit_signal,
        "pid": trial.pid,
        "unique_id": trial.unique_id,
        "kill_wall_ns": t_wall,
    }


def _stuck(running, what: str, error: Exception, victims: dict[int, str]) -> dict:
    """What to keep about a container that stopped answering: the error, its
    log's tail and, where gdb is installed, what its threads wait on."""
    out = {
        "profile": running.mode,
        "what": what,
        "error": str(error).splitlines()[0],
        "log_tail": log_tail(running.proc.log_text(), 40),
    }
    if diagnose.gdb_available() and running.proc.alive():
        try:
            d = diagnose.diagnose(running.proc.pid, nodes_by_pid=victims, dead_pids=set(victims))
            out["diagnosis"] = d.summary()
            out["stacks"] = d.stacks_text
        except Exception as exc:  # a diagnosis is a bonus; the trial is counted either way
            out["diagnosis"] = f"gdb failed: {type(exc).__name__}: {exc}"
    return out


def _start(session: Session, mode: str, others: int, replacing=None):
    """A container of ``mode`` (a fresh one for ``replacing``) with ``others`` idle nodes."""
    running = session.restart(replacing) if replacing is not None else session.start(mode)
    for k in range(others):
        timed_load(running, node_name=f"other{k}", parameters=HEARTBEAT_PARAMS, timeout=LOAD_TIMEOUT_S)
    return running


def measure(
    session: Session, profiles: list[str], signals: list[str], n: int, settle: float, recycle: int, others: int = 0
) -> dict:
    running = {p: _start(session, p, others) for p in profiles}
    crashes = {p: 0 for p in profiles}
    last: dict[str, str | None] = {p: None for p in profiles}  # the signal of the container's last crash
    victims: dict[str, dict[int, str]] = {p: {} for p in profiles}  # pid -> node name, this container's dead nodes
    data: dict[str, dict[str, dict[str, Any]]] = {
        p: {
            s: {
                "stamp": [],
                "client": [],
                "leak_logged": [],
                "died_logged": [],
                "lost": 0,
                "hung_after": 0,
                "wrong_signal": 0,
            }
            for s in signals
        }
        for p in profiles
    }
    stuck = []
    done = []  # (container process, its trial, the data it goes to)

    def fresh(p):
        running[p] = _start(session, p, others, replacing=running[p])
        crashes[p], last[p], victims[p] = 0, None, {}

    for i in range(n):
        for p in profiles:
            for s in signals:
                if crashes[p] >= recycle:
                    fresh(p)
                d = data[p][s]
                for _ in range(2):  # a load a hung container never answers: once more, fresh
                    try:
                        trial = _load(running[p], i)
                        break
                    except HarnessTimeout as exc:
                        what = f"LoadNode after a {last[p]} crash" if last[p] else "LoadNode, fresh container"
                        stuck.append(_stuck(running[p], what, exc, victims[p]))
                        previous = last[p]
                        if previous is not None:
                            data[p][previous]["hung_after"] += 1
                        fresh(p)
                else:
                    raise AssertionError(f"{label(p)}: a fresh container did not answer LoadNode either")
                try:
                    r = _crash(running[p], trial, signal.Signals[s], settle)
                except HarnessTimeout as exc:
                    d["lost"] += 1
                    stuck.append(_stuck(running[p], f"no CRASHED after {s}", exc, victims[p]))
                    fresh(p)
                    continue
                crashes[p] += 1
                last[p] = s
                victims[p][trial.pid] = f"victim{i}"
                done.append((running[p].proc, r, d))
                d["stamp"].append(r["stamp_ns"])
                d["client"].append(r["client_ns"])
                if r["exit_signal"] != signal.Signals[s]:
                    d["wrong_signal"] += 1
    for r in running.values():
        session.stop(r)
    _add_log_stamps(done)
    return {"trials": data, "stuck": stuck}


def _add_log_stamps(done: list[tuple]) -> None:
    """Where the time went, from the containers' own log stamps: each crash's
    'left in memory' and 'died' lines, into its data's leak_logged and
    died_logged (done: (container process, its trial, the data it goes to))."""
    logs = {}
    for proc, r, d in done:
        if proc.pid not in logs:
            logs[proc.pid] = log_stamps(proc.log_text())
        stamps = logs[proc.pid]
        for key, into in (("leak", "leak_logged"), ("died", "died_logged")):
            t = stamps.get((key, r["unique_id"]))
            if t is not None:
                d[into].append(t - r["kill_wall_ns"])


def _latency_table(data: dict, profiles: list[str], signals: list[str], n: int, others: int):
    """The first table (kill → CRASHED per profile and signal), its goals
    and summary rows."""
    table = Table(
        f"Container: os.kill() of a node's process → CRASHED (ms; n={n} per row, interleaved"
        + (f"; {others} other idle nodes in each container)" if others else ")"),
        [
            "profile",
            "signal",
            "n",
            "lost (no CRASHED in 10 s)",
            "container stuck afterwards (next LoadNode unanswered)",
            "→ CRASHED stamp: median",
            "stamp: p90",
            "stamp: max",
            "→ CRASHED at client: median",
            "at client: p90",
            f"median vs goal {GOAL_MS:g} ms",
        ],
    )
    goals, summary = [], []
    for p in profiles:
        for s in signals:
            d = data[p][s]
            st, cl = stats(ms(d["stamp"])), stats(ms(d["client"]))
            g = goal_at_most(GOAL, f"{label(p)}, {s}: kill → CRASHED stamp", st["median"], GOAL_MS, "ms")
            goals.append(g)
            table.add(
                label(p),
                s,
                st["n"],
                d["lost"],
                d["hung_after"],
                fmt_ms(st["median"]),
                fmt_ms(st["p90"]),
                fmt_ms(st["max"]),
                fmt_ms(cl["median"]),
                fmt_ms(cl["p90"]),
                g.verdict,
            )
            summary.append(
                summary_row(
                    "crash latency",
                    f"outside {s} → CRASHED (event stamp)",
                    label(p),
                    st,
                    goal=GOAL,
                    verdict=g.verdict,
                )
            )
    return table, goals, summary


def _steps_table(data: dict, profiles: list[str], signals: list[str]) -> Table:
    """The container's own stamps of a death: CRASHED and its log lines."""
    steps = Table(
        "On the container's side: its CRASHED stamp and the rcutils stamps of the log lines it "
        "writes about the death (ms from os.kill(); medians)",
        [
            "profile",
            "signal",
            "n",
            "CRASHED stamped (published)",
            "'died' error logged (manager)",
            "'left in memory' warning logged (host)",
        ],
    )
    for p in profiles:
        for s in signals:
            d = data[p][s]
            leak, died, st = stats(ms(d["leak_logged"])), stats(ms(d["died_logged"])), stats(ms(d["stamp"]))
            steps.add(label(p), s, st["n"], fmt_ms(st["median"]), fmt_ms(died["median"]), fmt_ms(leak["median"]))
    return steps


def _monitor_table(monitor: dict, n_monitor: int, summary: list[dict]) -> Table:
    """The standalone core's table (its summary rows appended to summary)."""
    mt = Table(
        f"Standalone CloneCore (worker process): os.kill() of an idle child → (ms; n={n_monitor})",
        [
            "signal",
            "n",
            "monitor detected: median",
            "detected: p90",
            "detected: max",
            "on_event called: median",
            "on_event: p90",
        ],
    )
    for s in ("SIGKILL", "SIGSEGV"):
        det, ev = stats(ms(monitor[f"{s}_monitor"])), stats(ms(monitor[f"{s}_on_event"]))
        mt.add(
            s,
            det["n"],
            fmt_ms(det["median"]),
            fmt_ms(det["p90"]),
            fmt_ms(det["max"]),
            fmt_ms(ev["median"]),
            fmt_ms(ev["p90"]),
        )
        summary.append(
            summary_row(
                "crash latency",
                f"outside {s} → monitor detected (standalone core)",
                "CloneCore",
                det,
                goal="(reference)",
            )
        )
    return mt


def _gap(data: dict, monitor: dict, profiles: list[str], signals: list[str]) -> str:
    """Where the standalone core and the container part, for SIGKILL ("": not measured)."""
    if not (monitor and "SIGKILL" in signals):
        return ""
    on_event = stats(ms(monitor["SIGKILL_on_event"]))["median"]
    stamped = [stats(ms(data[p]["SIGKILL"]["stamp"]))["median"] for p in profiles]
    if on_event is None or None in stamped:
        return ""
    return (
        f" For SIGKILL, a standalone core reaches on_event {fmt_ms(on_event)} ms after the kill; "
        f"the container stamps CRASHED at {' / '.join(fmt_ms(t) for t in stamped)} ms "
        f"({' / '.join(label(p).split(', ')[1] for p in profiles)}), so about "
        f"{' / '.join(fmt_ms(t - on_event) for t in stamped)} ms go between the core's listener "
        "and the publish."
    )


def _notes(
    data: dict, stuck: list, monitor: dict, profiles: list[str], signals: list[str], settle: float, recycle: int
) -> list[str]:
    gap = _gap(data, monitor, profiles, signals)
    lost = sum(data[p][s]["lost"] for p in profiles for s in signals)
    hung = sum(data[p][s]["hung_after"] for p in profiles for s in signals)
    wrong = sum(data[p][s]["wrong_signal"] for p in profiles for s in signals)
    notes = [
        "Kill time: time.time_ns() and time.monotonic_ns() in the benchmark just before os.kill(); the "
        "CRASHED stamp is the container's wall clock when it publishes the event (same host clock), "
        "the client time is when the benchmark's subscription callback recorded it.",
        "Path in the container: the C monitor's pidfd becomes readable → waitid → the repair → the "
        "monitor writes the death into the event (rosidl's message, made at the load) and hands it to "
        "the core's herald thread, which stamps and publishes it "
        "through rcl (isolated/clonecore/herald.c; no Python); the death's record goes on down a pipe to the core's "
        "listener thread → IsolatedHost → ComponentManager.on_death (the log lines). With a restart policy, "
        "or a death whose event only Python can word (it held the GIL, a protection-key fault, a core "
        "dump), the manager publishes it instead. The standalone table is only the first steps (monitor, "
        "on_event). The container-side "
        "table adds the rcutils wall-clock stamps of the two lines the container logs about the death "
        "(each also goes out on /rosout, a DDS publish of its own); which come before the publish depends "
        "on the container's code, the stamps say." + gap,
        "SIGSEGV from outside runs the child's crash report (its head written to the container's log, "
        "its Python and native stacks recorded raw) before it dies of the signal, so it takes longer "
        "than SIGKILL; the container writes both stacks after the CRASHED event.",
        f"Settle before the kill: {settle:g} s (the node is spinning). Each container is replaced after "
        f"{recycle} crashes, and when it stops answering. Lost trials (no CRASHED): {lost}; containers "
        f"that no longer answered LoadNode after a crash: {hung} (counted on the signal of that crash; "
        f"the trial is then run on a fresh container); CRASHED with another signal than the one sent: "
        f"{wrong}.",
    ]
    for k in stuck:
        notes.append(
            f"Stuck container ({label(k['profile'])}, {k['what']}): {k['error']}"
            + (f"; gdb: {k['diagnosis']}" if k.get("diagnosis") else "")
            + " (log tail and stacks in the JSON)."
        )
    return notes


def run(
    *,
    n: int = 100,
    n_monitor: int = 50,
    settle: float = 0.05,
    recycle: int = 25,
    others: int = 0,
    profiles: list[str] = PROFILES,
    signals: list[str] = SIGNALS,
    out=DEFAULT_OUT,
    keep_logs: bool = False,
    quiet: bool = False,
) -> Result:
    params = {
        "n": n,
        "n_monitor": n_monitor,
        "settle": settle,
        "recycle": recycle,
        "others": others,
        "profiles": list(profiles),
        "signals": list(signals),
        "out": str(out),
    }
    session = Session(NAME, keep_logs=keep_logs)
    try:
        measured = measure(session, list(profiles), list(signals), n, settle, recycle, others)
        data, stuck = measured["trials"], measured["stuck"]
        monitor = session.core_worker("kill", n_monitor) if n_monitor > 0 else {}
    finally:
        problems = session.close()

    table, goals, summary = _latency_table(data, profiles, signals, n, others)
    tables = [table, _steps_table(data, profiles, signals)]
    if monitor:
        tables.append(_monitor_table(monitor, n_monitor, summary))
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, {k: v for k, v in params.items() if k != "out"}),
        params,
        tables,
        goals,
        _notes(data, stuck, monitor, profiles, signals, settle, recycle),
        summary,
        {"container_ns": data, "stuck": stuck, "monitor_ns": monitor},
        problems,
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--n", type=int, default=100, help="trials per profile and signal (default: %(default)s)")
    parser.add_argument(
        "--n-monitor",
        type=int,
        default=50,
        help="standalone CloneCore trials per signal; 0: skip (default: %(default)s)",
    )
    parser.add_argument("--settle", type=float, default=0.05, help="seconds between LOADED and the kill")
    parser.add_argument("--recycle", type=int, default=25, help="crashes per container before a fresh one")
    parser.add_argument("--others", type=int, default=0, help="idle Heartbeat nodes loaded into each container first")
    parser.add_argument("--profiles", nargs="+", choices=PROFILES, default=PROFILES)
    parser.add_argument("--signals", nargs="+", choices=SIGNALS, default=SIGNALS)
    opts = parser.parse_args(argv)
    result = run(
        n=opts.n,
        n_monitor=opts.n_monitor,
        settle=opts.settle,
        recycle=opts.recycle,
        others=opts.others,
        profiles=opts.profiles,
        signals=opts.signals,
        out=opts.out,
        keep_logs=opts.keep_logs,
    )
    return 1 if result.cleanup else 0


if __name__ == "__main__":
    sys.exit(main())
