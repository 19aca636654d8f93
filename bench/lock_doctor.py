"""What the lock doctor (container/isolated/clonecore/mutexes.c) costs the monitor
thread, by the number of node processes.

    python -m cloneguard.bench.lock_doctor                  # 1, 10, 40 nodes
    python -m cloneguard.bench.lock_doctor --nodes 1 20 80 --threads 4 --seconds 10

For each count, a fresh worker process opens a CloneCore and spawns that many
children, each with ``threads`` threads besides its main task (as a node's
DDS threads), all idle. The monitor thread's CPU time (schedstat) is read
over ``seconds``:

before any death
    the doctor only looks at each child's tasks every 500 ms;
after a death
    one more child is spawned and SIGKILLed: from then on the doctor also
    reads every task's /proc/<tid>/syscall, every 500 ms (every 50 ms in the
    first second after the death, not in the window measured).

The figure is the monitor's CPU as a share of one CPU, and per task looked
at. Goal: under 1% of a CPU at 40 node processes after a death.

The held-mutex sweep (heldscan.c) a second after a death reads every
resident page of the container: ``--resident`` MiB (default 0, 256, 1024)
are made resident in a worker with one idle child, one more child is
SIGKILLed, and the monitor's CPU over the 2 s after the kill (the fast
first second of looks, then the sweep) is measured, with and without the
memory: the difference per MiB is the sweep's cost.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .goals import goal_at_most
from .results import Result, Table, summary_row

NAME = "lock_doctor"
TITLE = "Lock doctor: the monitor's CPU by the number of node processes"
GOAL_PERCENT = 1.0
GOAL_NODES = 40


def _monitor_tid() -> int:
    for tid in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{tid}/comm") as f:
            if f.read().strip() == "cg-monitor":
                return int(tid)
    raise RuntimeError("no cg-monitor thread")


def _cpu_ns(tid: int) -> int:
    with open(f"/proc/self/task/{tid}/schedstat") as f:
        return int(f.read().split()[0])


def _tasks(children) -> int:
    """Tasks the doctor looks at: the container's and every child's."""
    return len(os.listdir("/proc/self/task")) + sum(len(os.listdir(f"/proc/{c.pid}/task")) for c in children)


def worker(nodes: int, threads: int, seconds: float) -> dict:
    import rclpy  # noqa: F401  (a container-sized process)

    from cloneguard.container.isolated.core import CloneCore

    stop = threading.Event()

    def node():
        for _ in range(threads):
            threading.Thread(target=stop.wait, daemon=True).start()
        stop.wait()

    core = CloneCore()
    try:
        if not core.mitigations.mutex_repair:
            return {"unavailable": core.report.mutex_repair_unavailable}
        children = [core.spawn(node) for _ in range(nodes)]
        time.sleep(1.5)  # every thread started, and seen
        tid = _monitor_tid()
        tasks = _tasks(children)

        def cpu_share() -> float:
            t0, c0 = time.monotonic_ns(), _cpu_ns(tid)
            time.sleep(seconds)
            return (_cpu_ns(tid) - c0) / (time.monotonic_ns() - t0)

        before = cpu_share()
        victim = core.spawn(lambda: time.sleep(60))
        time.sleep(0.2)
        os.kill(victim.pid, signal.SIGKILL)
        core.wait(victim, timeout=10)
        core.release(victim)
        time.sleep(1.5)  # past the first, faster second
        after = cpu_share()
        stop.set()
        for c in children:
            core.wait(c, timeout=10)
            core.release(c)
        return {"nodes": nodes, "tasks": tasks, "before": before, "after": after}
    finally:
        core.close()


def sweep_worker(resident_mib: int) -> dict:
    """The monitor's CPU over the 2 s after a death, with ``resident_mib``
    MiB made resident first."""
    import rclpy  # noqa: F401  (a container-sized process)

    from cloneguard.container.isolated.core import CloneCore

    held = bytearray(b"\x01") * (resident_mib << 20)  # every page written: resident
    core = CloneCore()
    try:
        if not core.mitigations.mutex_repair:
            return {"unavailable": core.report.mutex_repair_unavailable}
        stop = threading.Event()
        idle = core.spawn(stop.wait)
        time.sleep(1.0)
        tid = _monitor_tid()
        victim = core.spawn(lambda: time.sleep(60))
        time.sleep(0.6)  # seen
        c0 = _cpu_ns(tid)
        os.kill(victim.pid, signal.SIGKILL)
        core.wait(victim, timeout=10)
        core.release(victim)
        time.sleep(2.0)
        cpu = _cpu_ns(tid) - c0
        with open("/proc/self/statm") as f:
            rss_mib = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / (1 << 20)
        stop.set()
        core.wait(idle, timeout=10)
        core.release(idle)
        return {"resident_mib": resident_mib, "rss_mib": rss_mib, "cpu_ms": cpu / 1e6, "held": len(held)}
    finally:
        core.close()


def _worker(*args: object, timeout: float) -> dict:
    done = subprocess.run(
        [sys.executable, "-m", "cloneguard.bench.lock_doctor", *map(str, args)],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    if done.returncode != 0:
        raise RuntimeError(f"lock_doctor worker {args} exited with {done.returncode}: {done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def run(
    *,
    nodes=(1, 10, 40),
    threads: int = 4,
    seconds: float = 5.0,
    resident=(0, 256, 1024),
    out=DEFAULT_OUT,
    keep_logs=False,
    quiet=False,
):
    params = {"nodes": list(nodes), "threads": threads, "seconds": seconds, "resident": list(resident), "out": str(out)}
    raw = [_worker("--worker", n, threads, seconds, timeout=120 + 4 * seconds) for n in nodes]
    sweeps = [_worker("--sweep-worker", mib, timeout=120) for mib in resident]
    if "unavailable" in raw[0]:
        raise RuntimeError(f"the lock doctor is unavailable here: {raw[0]['unavailable']}")
    table = Table(
        f"Monitor thread CPU, share of one CPU (over {seconds:g} s; children with {threads} idle threads each)",
        ["node processes", "tasks looked at", "before any death", "after a death", "after a death, per task"],
    )
    for r in raw:
        table.add(
            r["nodes"],
            r["tasks"],
            f"{r['before'] * 100:.3f}%",
            f"{r['after'] * 100:.3f}%",
            f"{r['after'] * 1e9 / r['tasks'] / 2:.0f} ns per task per look",
        )
    sweep_table = Table(
        "The held-mutex sweep: the monitor's CPU over the 2 s after a death, by the container's resident memory",
        ["resident memory made", "container RSS", "monitor CPU", "more than with none, per MiB"],
    )
    base = min(sweeps, key=lambda r: r["resident_mib"])
    for r in sweeps:
        extra = r["rss_mib"] - base["rss_mib"]
        per = f"{(r['cpu_ms'] - base['cpu_ms']) / extra * 1000:.0f} µs" if extra > 1 else "-"
        sweep_table.add(f"{r['resident_mib']} MiB", f"{r['rss_mib']:.0f} MiB", f"{r['cpu_ms']:.1f} ms", per)
    top = max(raw, key=lambda r: r["nodes"])
    goals = [
        goal_at_most(
            f"< {GOAL_PERCENT:g}% of a CPU at {GOAL_NODES} node processes after a death",
            f"monitor CPU after a death, {top['nodes']} node processes",
            top["after"] * 100 if top["nodes"] >= GOAL_NODES else None,
            GOAL_PERCENT,
            "%",
        )
    ]
    summary = [
        summary_row(
            "lock doctor",
            f"monitor CPU after a death, {top['nodes']} node processes ({top['tasks']} tasks)",
            "isolated (CloneCore)",
            {"n": 1},
            median=f"{top['after'] * 100:.3f}% of a CPU",
            p90="",
            goal=f"< {GOAL_PERCENT:g}%",
            verdict=goals[0].verdict,
        )
    ]
    notes = [
        "Per task per look: the CPU share after a death divided by the tasks and by the two looks a second.",
        "Idle children: a node that runs adds no work for the doctor (it reads /proc, not the node).",
    ]
    result = Result(
        NAME,
        TITLE,
        command_line(NAME, {"nodes": list(nodes), "threads": threads, "seconds": seconds, "resident": list(resident)}),
        params,
        [table, sweep_table],
        goals,
        notes,
        summary,
        {"runs": raw, "sweeps": sweeps},
        cleanup=[],
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--worker"]:
        print(json.dumps(worker(int(argv[1]), int(argv[2]), float(argv[3]))))
        return 0
    if argv[:1] == ["--sweep-worker"]:
        print(json.dumps(sweep_worker(int(argv[1]))))
        return 0
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--nodes", type=int, nargs="+", default=[1, 10, 40])
    parser.add_argument("--threads", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--resident", type=int, nargs="+", default=[0, 256, 1024], metavar="MIB")
    opts = parser.parse_args(argv)
    run(nodes=opts.nodes, threads=opts.threads, seconds=opts.seconds, resident=opts.resident, out=opts.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
