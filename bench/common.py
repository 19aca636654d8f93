"""What every benchmark shares: starting and stopping what it measures,
statistics, goals and the report files.

Containers are the real ``component_container``, launched the way the
harness launches them (``harness.process.ContainerProcess``: setpriv
--pdeathsig, own session, the no-SHM Fast DDS profile), each on a ROS domain
of its own (``harness.domains.lease()``), driven by
``harness.client.ContainerClient``. A :class:`Session` owns everything one
benchmark starts and stops all of it, then checks that nothing is left.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import select
import shlex
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from cloneguard.harness import domains, procfs, shm
from cloneguard.harness.process import NO_SHM_PROFILE, REPO_ROOT, ContainerProcess, process_environment, use_loopback_ros

# The benchmark's own participant (its clients) runs under the same rules as
# the containers: UDP on loopback only. Set before any rclpy.init.
use_loopback_ros()

from cloneguard.harness.client import ContainerClient, HarnessTimeout, Received  # noqa: E402
from cloneguard.harness.factory import log_tail, wait_ready  # noqa: E402
from cloneguard.harness.report.env import git_info, host_info, python_version  # noqa: E402

DEFAULT_OUT = REPO_ROOT / "reports" / "bench"
PACKAGE = "cloneguard"
HEARTBEAT = "cloneguard::Heartbeat"
LISTENER = "cloneguard::Listener"       # no timer: idle unless a message arrives

# Container modes: key -> (label, container arguments).
MODES = {
    "isolated-per-node": ("isolated, per-node profile", ["--isolated", "--profile", "per-node"]),
    "isolated-shared": ("isolated, shared profile", ["--isolated", "--profile", "shared"]),
    "thread": ("thread mode (single-threaded executor)", []),
    "thread-mt": ("thread mode (multi-threaded executor)", ["--use_multi_threaded_executor"]),
}
PROCESS_PER_NODE = "process-per-node"
PROCESS_PER_NODE_LABEL = "process per node (fork+exec, bench.process_per_node)"


def label(mode: str) -> str:
    return PROCESS_PER_NODE_LABEL if mode == PROCESS_PER_NODE else MODES[mode][0]


# -- statistics ------------------------------------------------------------------

def stats(values: list[float]) -> dict:
    """n, median, p90 (inclusive quantiles), min, max of ``values``."""
    vals = sorted(v for v in values if v is not None and not math.isnan(v))
    if not vals:
        return {"n": 0, "median": None, "p90": None, "min": None, "max": None}
    p90 = statistics.quantiles(vals, n=10, method="inclusive")[-1] if len(vals) > 1 else vals[0]
    return {"n": len(vals), "median": statistics.median(vals), "p90": p90, "min": vals[0], "max": vals[-1]}


def ms(ns_values: list[int]) -> list[float]:
    return [v / 1e6 for v in ns_values]


def fmt_ms(x: float | None) -> str:
    if x is None:
        return "–"
    if x >= 100:
        return f"{x:.0f}"
    if x >= 10:
        return f"{x:.1f}"
    if x >= 1:
        return f"{x:.2f}"
    return f"{x:.3f}"


def fmt_ratio(x: float | None) -> str:
    if x is None or math.isinf(x) or math.isnan(x):
        return "–"
    return f"{x:.0f}×" if x >= 10 else f"{x:.1f}×"


def ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or b <= 0:
        return None
    return a / b


# -- goals -----------------------------------------------------------------------

@dataclass
class Goal:
    goal: str           # what was asked, e.g. "median ≤ 1 ms"
    measure: str        # what it is judged on
    measured: str       # the figure, formatted
    met: bool | None    # None: could not be measured
    verdict: str        # "met", or by how much it is missed

    def row(self) -> dict:
        return {"goal": self.goal, "judged on": self.measure, "measured": self.measured, "verdict": self.verdict}


def goal_at_most(goal: str, measure: str, value: float | None, limit: float, unit: str) -> Goal:
    if value is None:
        return Goal(goal, measure, "–", None, "not measured")
    shown = f"{fmt_ms(value)} {unit}"
    if value <= limit:
        return Goal(goal, measure, shown, True, "met")
    return Goal(goal, measure, shown, False,
                f"missed by {fmt_ms(value - limit)} {unit} ({fmt_ratio(value / limit)} the goal)")


def goal_at_least_ratio(goal: str, measure: str, value: float | None, target: float) -> Goal:
    if value is None:
        return Goal(goal, measure, "–", None, "not measured")
    if value >= target:
        return Goal(goal, measure, fmt_ratio(value), True, "met")
    short = target / value
    return Goal(goal, measure, fmt_ratio(value), False,
                f"missed: {fmt_ratio(value)} of {fmt_ratio(target)} "
                f"({f'{short:.2f}×' if short < 2 else fmt_ratio(short)} short)")


# -- report ----------------------------------------------------------------------

@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[dict] = field(default_factory=list)

    def __post_init__(self):
        if len(set(self.columns)) != len(self.columns):
            raise ValueError(f"{self.title}: column names must be distinct: {self.columns}")

    def add(self, *cells) -> None:
        if len(cells) != len(self.columns):
            raise ValueError(f"{self.title}: {len(cells)} cells for {len(self.columns)} columns")
        self.rows.append(dict(zip(self.columns, (str(c) for c in cells))))

    def markdown(self) -> str:
        def esc(s: str) -> str:
            return s.replace("|", "\\|")
        lines = ["| " + " | ".join(esc(c) for c in self.columns) + " |",
                 "|" + "|".join("---" for _ in self.columns) + "|"]
        lines += ["| " + " | ".join(esc(r[c]) for c in self.columns) + " |" for r in self.rows]
        return "\n".join(lines)

    def as_json(self) -> dict:
        return {"title": self.title, "columns": self.columns, "rows": self.rows}


def host() -> dict:
    info = host_info()
    info["python"] = python_version()
    info["date"] = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    info["git"] = git_info(REPO_ROOT)
    return info


def host_line(info: dict) -> str:
    git = info.get("git") or {}
    commit = (git.get("commit") or "?")[:10] + (" (with uncommitted changes)" if git.get("dirty") else "")
    return (f"kernel {info['kernel']} ({info['machine']}), CPU {info['cpu_model']} "
            f"({info['cpu_count']} CPUs, {info['cpu_usable']} usable), {info['glibc']}, "
            f"{info['python']}, git {commit}, {info['date']}")


@dataclass
class Result:
    name: str
    title: str
    command: str
    params: dict
    tables: list[Table]
    goals: list[Goal]
    notes: list[str]
    summary: list[dict]         # rows for summary.md (see SUMMARY_COLUMNS)
    raw: dict
    cleanup: list[str]          # problems found after clean-up; [] when clean
    host: dict = field(default_factory=host)

    def markdown(self) -> str:
        out = [f"# {self.title}", "",
               f"Command (from the repository root, venv active): `{self.command}`", "",
               f"Host: {host_line(self.host)}", ""]
        for table in self.tables:
            out += [f"## {table.title}", "", table.markdown(), ""]
        if self.goals:
            goals = Table("Goals", ["goal", "judged on", "measured", "verdict"])
            for g in self.goals:
                goals.add(*g.row().values())
            out += ["## Goals", "", goals.markdown(), ""]
        if self.notes:
            out += ["## Method and notes", ""] + [f"- {n}" for n in self.notes] + [""]
        out += ["Clean-up: " + ("every container stopped, no process or /dev/shm segment left."
                                if not self.cleanup else "PROBLEMS: " + "; ".join(self.cleanup)), ""]
        return "\n".join(out)

    def as_json(self) -> dict:
        return {
            "name": self.name, "title": self.title, "command": self.command,
            "invoked_as": shlex.join([Path(sys.executable).name, *sys.argv]),
            "host": self.host, "params": self.params,
            "tables": [t.as_json() for t in self.tables],
            "goals": [{"goal": g.goal, "judged_on": g.measure, "measured": g.measured,
                       "met": g.met, "verdict": g.verdict} for g in self.goals],
            "notes": self.notes, "summary": self.summary, "cleanup": self.cleanup, "raw": self.raw,
        }

    def write(self, out_dir: Path) -> tuple[Path, Path]:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        md, js = out_dir / f"{self.name}.md", out_dir / f"{self.name}.json"
        md.write_text(self.markdown())
        js.write_text(json.dumps(self.as_json(), indent=1) + "\n")
        return md, js


SUMMARY_COLUMNS = ["benchmark", "measure", "mode", "n", "median", "p90", "goal", "verdict"]


def summary_row(benchmark: str, measure: str, mode: str, st: dict | None, unit: str = "ms",
                goal: str = "", verdict: str = "", median: str | None = None, p90: str | None = None) -> dict:
    st = st or {}
    return {
        "benchmark": benchmark, "measure": measure, "mode": mode, "n": str(st.get("n", "")),
        "median": median if median is not None else (f"{fmt_ms(st.get('median'))} {unit}" if st else ""),
        "p90": p90 if p90 is not None else (f"{fmt_ms(st.get('p90'))} {unit}" if st else ""),
        "goal": goal, "verdict": verdict,
    }


# -- command line ----------------------------------------------------------------

def arg_parser(name: str, description: str) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=f"python -m cloneguard.bench.{name}", description=description)
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT,
                        help="directory for <name>.md and <name>.json (default: reports/bench)")
    parser.add_argument("--keep-logs", action="store_true",
                        help="keep the container logs (their directory is printed)")
    return parser


def command_line(name: str, args: dict) -> str:
    """The command that repeats a run with these parameters."""
    parts = ["python", "-m", f"cloneguard.bench.{name}"]
    for key, value in args.items():
        flag = "--" + key.replace("_", "-")
        if isinstance(value, bool):
            if value:
                parts.append(flag)
        elif isinstance(value, (list, tuple)):
            parts += [flag, *[str(v) for v in value]]
        else:
            parts += [flag, str(value)]
    return shlex.join(parts)


def finish(result: Result, out_dir: Path, *, quiet: bool = False) -> Result:
    md, js = result.write(out_dir)
    if not quiet:
        print(result.markdown())
        print(f"wrote {md} and {js}")
    return result


# -- what a benchmark starts -------------------------------------------------------

@dataclass
class Running:
    """A started container, its client and its domain."""

    mode: str
    proc: ContainerProcess
    client: ContainerClient
    lease: domains.DomainLease
    label: str

    @property
    def domain_id(self) -> int:
        return self.lease.domain_id


class NodeProcess:
    """One ``bench.process_per_node`` runner: fork+exec'd, own session."""

    def __init__(self, domain_id: int, log_path: Path, *, package: str = PACKAGE,
                 plugin: str = HEARTBEAT, node_name: str = ""):
        env = process_environment(domain_id, fastdds_profile=NO_SHM_PROFILE)
        env["PYTHONUNBUFFERED"] = "1"
        r, w = os.pipe2(os.O_CLOEXEC)
        argv = [sys.executable, "-m", "cloneguard.bench.process_per_node", "--ready-fd", str(w),
                "--parent", str(os.getpid()), package, plugin]
        if node_name:
            argv[-2:-2] = ["--node-name", node_name]
        self.log_path = Path(log_path)
        self._log = open(self.log_path, "ab", buffering=0)
        self._ready_r = r
        self.spawn_ns = time.monotonic_ns()
        try:
            self.popen = subprocess.Popen(
                argv, cwd=REPO_ROOT, env=env, stdin=subprocess.DEVNULL, stdout=self._log,
                stderr=subprocess.STDOUT, pass_fds=(w,), start_new_session=True,
            )
        finally:
            os.close(w)
        self.pid = self.pgid = self.popen.pid
        self.ready: dict | None = None

    def wait_ready(self, timeout: float = 60.0) -> dict:
        """The runner's ready stamps, plus ``read_ns`` (when we read them)."""
        buf = b""
        deadline = time.monotonic() + timeout
        while not buf.endswith(b"\n"):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self._ready_r], [], [], left)[0]:
                raise HarnessTimeout(f"runner {self.pid} not ready within {timeout:.0f} s\n"
                                     + log_tail(self.log_path.read_text(errors="replace")))
            chunk = os.read(self._ready_r, 4096)
            if not chunk:
                raise AssertionError(f"runner {self.pid} exited before it was ready (code "
                                     f"{self.popen.wait()})\n"
                                     + log_tail(self.log_path.read_text(errors="replace")))
            buf += chunk
        read_ns = time.monotonic_ns()
        self.ready = dict(json.loads(buf.decode().split(" ", 1)[1]), read_ns=read_ns, spawn_ns=self.spawn_ns)
        return self.ready

    def stop(self, grace: float = 3.0) -> int:
        if self._ready_r >= 0:
            os.close(self._ready_r)
            self._ready_r = -1
        if self.popen.poll() is None:
            _killpg(self.pgid, signal.SIGTERM)
            try:
                self.popen.wait(grace)
            except subprocess.TimeoutExpired:
                _killpg(self.pgid, signal.SIGKILL)
        code = self.popen.wait()
        if procfs.pids_in_group(self.pgid):
            _killpg(self.pgid, signal.SIGKILL)
            procfs.wait_group_empty(self.pgid, timeout=grace)
        self._log.close()
        return code


def _killpg(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except ProcessLookupError:
        pass


class Session:
    """Everything one benchmark run starts; :meth:`close` stops it all and
    returns what was left behind (nothing, if all went well)."""

    def __init__(self, name: str, *, keep_logs: bool = False):
        self.log_dir = Path(tempfile.mkdtemp(prefix=f"cloneguard-bench-{name}-"))
        self.keep_logs = keep_logs
        self._running: list[Running] = []
        self._runners: list[NodeProcess] = []
        self._leases: list[domains.DomainLease] = []
        self._pgids: list[int] = []
        self._shm_before = shm.segments()
        self._count = 0
        self.closed = False

    def _log_path(self, stem: str) -> Path:
        self._count += 1
        return self.log_dir / f"{self._count:03d}-{stem}.log"

    def lease(self) -> domains.DomainLease:
        lease = domains.lease()
        self._leases.append(lease)
        return lease

    def release(self, lease: domains.DomainLease) -> None:
        lease.release()
        if lease in self._leases:
            self._leases.remove(lease)

    def start(self, mode: str, *, extra_args: list[str] = ()) -> Running:
        """Start a container in ``mode`` on a domain of its own; return once it answers."""
        lease = self.lease()
        proc = ContainerProcess([*MODES[mode][1], *extra_args], domain_id=lease.domain_id,
                                log_path=self._log_path(f"container-{mode}"))
        self._pgids.append(proc.pgid)
        cli = ContainerClient(lease.domain_id, proc.fqn, name=f"bench_{os.getpid()}_{self._count}")
        running = Running(mode, proc, cli, lease, label(mode))
        self._running.append(running)
        wait_ready(cli, proc)
        return running

    def stop(self, running: Running):
        """Client closed, container stopped (ContainerProcess.stop), domain released."""
        running.client.close()
        status = running.proc.stop()
        self.release(running.lease)
        if running in self._running:
            self._running.remove(running)
        return status

    def restart(self, running: Running) -> Running:
        self.stop(running)
        return self.start(running.mode)

    def runner(self, domain_id: int, *, node_name: str = "", plugin: str = HEARTBEAT) -> NodeProcess:
        r = NodeProcess(domain_id, self._log_path(f"runner-{node_name or 'node'}"), plugin=plugin,
                        node_name=node_name)
        self._pgids.append(r.pgid)
        self._runners.append(r)
        return r

    def stop_runner(self, r: NodeProcess) -> int:
        code = r.stop()
        if r in self._runners:
            self._runners.remove(r)
        return code

    def core_worker(self, what: str, n: int, timeout: float = 600.0) -> dict:
        """Run ``python -m cloneguard.bench._core_worker`` (its own CloneCore) and return its JSON."""
        log = self._log_path(f"core-worker-{what}")
        with open(log, "wb") as err:
            done = subprocess.run([sys.executable, "-m", "cloneguard.bench._core_worker", what, "--n", str(n)],
                                  cwd=REPO_ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                  stderr=err, timeout=timeout, check=False)
        if done.returncode != 0:
            raise RuntimeError(f"cloneguard.bench._core_worker {what} exited with {done.returncode}\n"
                               + log_tail(log.read_text(errors="replace")))
        return json.loads(done.stdout)

    def close(self) -> list[str]:
        """Stop everything still running; return what was left behind."""
        if self.closed:
            return []
        self.closed = True
        for running in list(self._running):
            try:
                self.stop(running)
            except Exception as exc:   # keep stopping the rest
                print(f"bench: stopping {running.label}: {exc}", file=sys.stderr)
        for r in list(self._runners):
            self.stop_runner(r)
        for lease in list(self._leases):
            self.release(lease)
        problems = []
        for pgid in self._pgids:
            if not procfs.wait_group_empty(pgid, timeout=2.0):
                problems.append(f"processes left in group {pgid}: {procfs.pids_in_group(pgid)}")
        zombies = procfs.zombies_of(os.getpid())
        if zombies:
            problems.append(f"zombie children of the benchmark: {zombies}")
        new = shm.segments() - self._shm_before
        orphans = [seg.name for seg in shm.classify(new) if seg.orphan]
        if orphans:
            problems.append(f"orphaned /dev/shm segments appeared: {orphans}")
        if self.keep_logs or problems:
            print(f"bench: logs kept in {self.log_dir}", file=sys.stderr)
        else:
            shutil.rmtree(self.log_dir, ignore_errors=True)
        return problems

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# -- LoadNode ---------------------------------------------------------------------

def event_received(cli: ContainerClient, event_type: int, unique_id: int, timeout: float) -> Received:
    """Wait for an event of ``unique_id``; return it with when the client got it."""
    msg = cli.events.wait_for(
        lambda ev: ev.event_type == event_type and ev.unique_id == unique_id, timeout,
        f"event {event_type} for unique_id {unique_id}")
    for item in cli.events.items():
        if item.msg is msg:
            return item
    raise AssertionError("event seen but not recorded")


def stamp_ns(msg) -> int:
    return msg.stamp.sec * 1_000_000_000 + msg.stamp.nanosec


@dataclass
class LoadTrial:
    unique_id: int
    pid: int
    round_trip_ns: int          # LoadNode request sent -> response received
    loaded_ns: int              # request sent -> LOADED received by the client
    published_ns: int           # request sent (wall clock) -> LOADED's stamp (container's wall clock)


def timed_load(running: Running, *, node_name: str = "", plugin: str = HEARTBEAT,
               timeout: float = 30.0) -> LoadTrial:
    """One LoadNode (a Heartbeat by default), timed from the moment the request is sent."""
    from cloneguard_interfaces.msg import ComponentEvent

    cli = running.client
    send_wall = time.time_ns()
    send = time.monotonic_ns()
    resp = cli.load(PACKAGE, plugin, node_name=node_name, timeout=timeout)
    answered = time.monotonic_ns()
    if not resp.success:
        raise AssertionError(f"LoadNode failed in {running.label}: {resp.error_message}")
    item = event_received(cli, ComponentEvent.LOADED, resp.unique_id, timeout)
    return LoadTrial(resp.unique_id, item.msg.pid, answered - send, item.at_ns - send,
                     stamp_ns(item.msg) - send_wall)


def timed_unload(running: Running, unique_id: int, timeout: float = 30.0) -> int:
    t0 = time.monotonic_ns()
    resp = running.client.unload(unique_id, timeout=timeout)
    t1 = time.monotonic_ns()
    if not resp.success:
        raise AssertionError(f"UnloadNode {unique_id} failed in {running.label}: {resp.error_message}")
    return t1 - t0
