"""Long life: does a container drain itself over hundreds of loads?

Per mode, one container; a cycle is one load and unload of a valid node and
two failed constructions: a Heartbeat whose constructor refuses its period,
and one whose ``Node.__init__`` refuses a built-in parameter of the wrong
type (``use_sim_time`` as a string: rclpy raises before the node is whole).
After ``warmup`` cycles (pools and caches fill), the container's RSS (its
address space, which its node processes share), open fds and threads (its
own thread group; its child processes are counted apart and must be none
at rest but the per-node profile's warm spare) are read, then again after ``cycles`` more. The figures are growth
per cycle.

A crash loop is measured apart (``--crash-cycles``): a node that dies in
its first callback (SIGSEGV), loaded again at once after each death, as a
restart policy reloads it but without its backoff. Every crash leaves the
dead process's objects in memory on purpose (container/isolated/host.py),
so this growth is per crash, not a leak of the container's own; the restart
policy's limit (container/restart.py) bounds how many a node can leave.

    python -m cloneguard.bench.leaks [--cycles 300] [--warmup 40] [--modes threads per-node shared cgroups]
                                     [--crash-cycles 200] [--crash-modes per-node shared]

tests/test_leaks.py runs the same with small counts and asserts the bounds
(RSS <= LIMIT_MIB_PER_CYCLE per cycle, fds and threads +0).
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field

from cloneguard_interfaces.msg import ComponentEvent

from cloneguard.faults import PACKAGE
from cloneguard.harness import domains, procfs, rest
from cloneguard.harness.factory import ContainerFactory
from cloneguard.harness.process import use_loopback_ros

from .cli import arg_parser, command_line, finish
from .goals import Goal
from .results import Result, Table

# The benchmark's own participant (the factory's clients) runs under the same
# rules as the containers: UDP on loopback only. Set before any rclpy.init.
use_loopback_ros()

MODES = {
    "threads": [],
    "per-node": ["--isolated", "--profile", "per-node"],
    "shared": ["--isolated", "--profile", "shared"],
    "cgroups": ["--isolated", "--cgroups"],
}
LIMIT_MIB_PER_CYCLE = 0.05
# Child processes a container keeps at rest: the per-node profile's warm
# spare (container/isolated/spare.py), the next node's process made ahead.
PROCESSES_AT_REST = {"per-node": 1}
# Modes whose nodes can crash alone, and the crashes before the first sample.
CRASH_MODES = ("per-node", "shared")
CRASH_WARMUP = 5
PKG, NODE = "cloneguard", "cloneguard::Heartbeat"
# The crash loop's node: a SIGSEGV in its first timer callback.
TESTRIG, CRASHER = PACKAGE, "faults::SegfaultInCallback"


@dataclass
class Sample:
    rss_kib: int
    fds: int
    threads: int
    child_processes: int
    fd_targets: dict[int, str] = field(default_factory=dict, repr=False)  # fd: what it names


@dataclass
class Growth:
    mode: str
    cycles: int
    before: Sample
    after: Sample

    @property
    def rss_mib_per_cycle(self) -> float:
        return (self.after.rss_kib - self.before.rss_kib) / 1024 / self.cycles

    @property
    def fds(self) -> int:
        return self.after.fds - self.before.fds

    def new_fds(self) -> dict[int, str]:
        """The fds open at the end that were not (or named something else) at the start."""
        before = self.before.fd_targets
        return {fd: t for fd, t in self.after.fd_targets.items() if before.get(fd) != t}

    @property
    def threads(self) -> int:
        return self.after.threads - self.before.threads


def sample(pid: int, client, mode: str) -> Sample:
    """After a moment to settle (threads that end a request exit), and with
    the per-node profile's spare made (it shares the container's fds)."""
    time.sleep(0.5)
    rest.wait_at_rest(client.node, pid, spare=PROCESSES_AT_REST.get(mode, 0) > 0)
    fds = procfs.lasting_fds(pid)
    return Sample(
        rss_kib=procfs.rss_kib(pid),
        fds=len(fds),
        fd_targets=fds,
        threads=len(os.listdir(f"/proc/{pid}/task")),
        child_processes=len(procfs.children_of(pid)),
    )


def cycle(client) -> None:
    uid = client.load_ok(PKG, NODE, node_name="cycled").unique_id
    if not client.unload(uid).success:
        raise AssertionError(f"unload of {uid} failed")
    for parameters in ({"period": -1.0}, {"use_sim_time": "yes"}):
        resp = client.load(PKG, NODE, node_name="refused", parameters=parameters)
        if resp.success:
            raise AssertionError(f"a Heartbeat with {parameters} was loaded")


def crash_cycle(client) -> None:
    """One crash of a node that dies as soon as it runs (what a restart
    policy reloads over and over): load it, wait for its CRASHED."""
    uid = client.load_ok(TESTRIG, CRASHER, node_name="crasher", parameters={"delay": 0.01}).unique_id
    client.wait_for_event(ComponentEvent.CRASHED, unique_id=uid, timeout=20)


def measure_crashes(mode: str, cycles: int, warmup: int, log_dir) -> Growth:
    """Growth per crash: every crashed node's process leaves its node,
    executor (and, per-node, DDS participant) in memory, on purpose."""
    return _growth(mode, cycles, warmup, log_dir, crash_cycle)


def burst(client, n: int = 16) -> None:
    """Concurrent requests, so that the container's thread pools (services,
    builders) reach the size they are bounded to before anything is counted."""
    threads = [threading.Thread(target=cycle, args=(client,)) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def measure(mode: str, cycles: int, warmup: int, log_dir) -> Growth:
    """Growth per load/unload cycle (with two refused loads), after a burst
    that grows the container's thread pools to their bounds."""
    return _growth(mode, cycles, warmup, log_dir, cycle, first=burst)


def _growth(mode: str, cycles: int, warmup: int, log_dir, step, first=None) -> Growth:
    """A fresh container of ``mode``: ``first(client)``, ``warmup`` steps,
    a sample, ``cycles`` steps, a sample."""
    with domains.lease() as lease:
        factory = ContainerFactory(lease.domain_id, log_dir)
        try:
            proc = factory.start(MODES[mode])
            client = factory.connect(proc)
            if first is not None:
                first(client)
            for _ in range(warmup):
                step(client)
            before = sample(proc.pid, client, mode)
            for _ in range(cycles):
                step(client)
            after = sample(proc.pid, client, mode)
        finally:
            factory.stop_all()
    return Growth(mode, cycles, before, after)


def main(argv: list[str] | None = None) -> int:
    import tempfile

    parser = arg_parser("leaks", __doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=40)
    parser.add_argument("--modes", nargs="+", choices=sorted(MODES), default=list(MODES))
    parser.add_argument("--crash-cycles", type=int, default=200, help="crashes per crash-loop mode (0: none)")
    parser.add_argument("--crash-modes", nargs="+", choices=sorted(CRASH_MODES), default=list(CRASH_MODES))
    args = parser.parse_args(argv)
    table = Table(
        "Growth at rest, per cycle (one load+unload and two failed constructions)",
        [
            "mode",
            "cycles",
            "RSS before",
            "RSS after",
            "RSS per cycle",
            "fds",
            "threads",
            "child processes at rest (expected)",
            "goal",
            "verdict",
        ],
    )
    raw: dict = {}
    goals: list[Goal] = []
    with tempfile.TemporaryDirectory(prefix="cloneguard-leaks-") as logs:
        for mode in args.modes:
            g = measure(mode, args.cycles, args.warmup, logs)
            raw[mode] = {"before": g.before.__dict__, "after": g.after.__dict__}
            resting = PROCESSES_AT_REST.get(mode, 0)
            ok = (
                g.rss_mib_per_cycle <= LIMIT_MIB_PER_CYCLE
                and g.fds <= 0
                and g.threads <= 0
                and g.after.child_processes == resting
            )
            table.add(
                mode,
                g.cycles,
                f"{g.before.rss_kib / 1024:.1f} MiB",
                f"{g.after.rss_kib / 1024:.1f} MiB",
                f"{g.rss_mib_per_cycle:+.4f} MiB",
                f"{g.fds:+d}",
                f"{g.threads:+d}",
                f"{g.after.child_processes} ({resting})",
                f"≤ {LIMIT_MIB_PER_CYCLE} MiB, fds/threads +0",
                "met" if ok else "missed",
            )
        crashes = Table(
            "Growth per crash (a node that dies in its first callback, loaded again at once)",
            [
                "mode",
                "crashes",
                "RSS before",
                "RSS after",
                "RSS per crash",
                "fds per crash",
                "threads",
                "child processes at rest (expected)",
            ],
        )
        for mode in args.crash_modes if args.crash_cycles > 0 else ():
            g = measure_crashes(mode, args.crash_cycles, CRASH_WARMUP, logs)
            raw[f"crash-loop {mode}"] = {"before": g.before.__dict__, "after": g.after.__dict__}
            crashes.add(
                mode,
                g.cycles,
                f"{g.before.rss_kib / 1024:.1f} MiB",
                f"{g.after.rss_kib / 1024:.1f} MiB",
                f"{g.rss_mib_per_cycle:+.2f} MiB",
                f"{g.fds / g.cycles:+.1f}",
                f"{g.threads:+d}",
                f"{g.after.child_processes} ({PROCESSES_AT_REST.get(mode, 0)})",
            )
    params = {
        "cycles": args.cycles,
        "warmup": args.warmup,
        "modes": args.modes,
        "crash_cycles": args.crash_cycles,
        "crash_modes": args.crash_modes,
    }
    result = Result(
        name="leaks",
        title="Long life: growth per load cycle, and per crash",
        command=command_line("leaks", params),
        params=params,
        tables=[table, crashes],
        goals=goals,
        notes=[
            "RSS is the container's (VmRSS of its pid): its node processes share its address space.",
            "Threads and fds are the container's own thread group's; node processes are counted apart.",
            "A crash leaves the dead process's node and executor (per-node: and its DDS participant, "
            "with its sockets) in memory on purpose; --restart-limit bounds how many one node leaves.",
        ],
        summary=[],
        raw=raw,
        cleanup=[],
    )
    finish(result, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
