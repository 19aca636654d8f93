"""What a benchmark starts, and the stopping of all of it.

Containers are the real ``component_container``, launched the way the
harness launches them (``harness.process.ContainerProcess``: setpriv
--pdeathsig, own session, the no-SHM Fast DDS profile), each on a ROS domain
of its own (``harness.domains.lease()``), driven by
``harness.client.ContainerClient``; process-per-node runners are
``bench.process_per_node`` processes (:class:`NodeProcess`). A
:class:`Session` owns everything one benchmark starts and stops all of it,
then checks that nothing is left.

Importing this module sets up the benchmark's own ROS environment (UDP on
loopback only), before any rclpy.init.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cloneguard.harness import domains, procfs, shm
from cloneguard.harness.process import (
    NO_SHM_PROFILE,
    REPO_ROOT,
    ContainerProcess,
    process_environment,
    stop_group,
    use_loopback_ros,
)

# The benchmark's own participant (its clients) runs under the same rules as
# the containers: UDP on loopback only. Set before any rclpy.init.
use_loopback_ros()

from cloneguard.harness.client import ContainerClient, HarnessTimeout  # noqa: E402
from cloneguard.harness.factory import log_tail, wait_ready  # noqa: E402

from .discovery_server import DiscoveryServer  # noqa: E402
from .modes import HEARTBEAT, MODES, PACKAGE, label  # noqa: E402


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

    def __init__(
        self,
        domain_id: int,
        log_path: Path,
        *,
        package: str = PACKAGE,
        plugin: str = HEARTBEAT,
        node_name: str = "",
        params: dict | None = None,
    ):
        env = process_environment(domain_id, fastdds_profile=NO_SHM_PROFILE)
        env["PYTHONUNBUFFERED"] = "1"
        r, w = os.pipe2(os.O_CLOEXEC)
        argv = [
            sys.executable,
            "-m",
            "cloneguard.bench.process_per_node",
            "--ready-fd",
            str(w),
            "--parent",
            str(os.getpid()),
            package,
            plugin,
        ]
        if node_name:
            argv[-2:-2] = ["--node-name", node_name]
        for key, value in (params or {}).items():
            argv[-2:-2] = ["--param", f"{key}:={value}"]
        self.log_path = Path(log_path)
        self._log = open(self.log_path, "ab", buffering=0)
        self._ready_r = r
        self.spawn_ns = time.monotonic_ns()
        try:
            self.popen = subprocess.Popen(
                argv,
                cwd=REPO_ROOT,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=self._log,
                stderr=subprocess.STDOUT,
                pass_fds=(w,),
                start_new_session=True,
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
                raise HarnessTimeout(
                    f"runner {self.pid} not ready within {timeout:.0f} s\n"
                    + log_tail(self.log_path.read_text(errors="replace"))
                )
            chunk = os.read(self._ready_r, 4096)
            if not chunk:
                raise AssertionError(
                    f"runner {self.pid} exited before it was ready (code "
                    f"{self.popen.wait()})\n" + log_tail(self.log_path.read_text(errors="replace"))
                )
            buf += chunk
        read_ns = time.monotonic_ns()
        self.ready = dict(json.loads(buf.decode().split(" ", 1)[1]), read_ns=read_ns, spawn_ns=self.spawn_ns)
        return self.ready

    def stop(self, grace: float = 3.0) -> int:
        if self._ready_r >= 0:
            os.close(self._ready_r)
            self._ready_r = -1
        code, _ = stop_group(self.popen, self.pgid, grace)
        self._log.close()
        return code


class Session:
    """Everything one benchmark run starts; :meth:`close` stops it all and
    returns what was left behind (nothing, if all went well)."""

    def __init__(self, name: str, *, keep_logs: bool = False):
        self.log_dir = Path(tempfile.mkdtemp(prefix=f"cloneguard-bench-{name}-"))
        self.keep_logs = keep_logs
        self._running: list[Running] = []
        self._runners: list[NodeProcess] = []
        self._servers: list[DiscoveryServer] = []
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

    def start(self, mode: str, *, extra_args: Sequence[str] = ()) -> Running:
        """Start a container in ``mode`` on a domain of its own; return once it answers."""
        lease = self.lease()
        proc = ContainerProcess(
            [*MODES[mode][1], *extra_args], domain_id=lease.domain_id, log_path=self._log_path(f"container-{mode}")
        )
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

    def runner(
        self, domain_id: int, *, node_name: str = "", plugin: str = HEARTBEAT, params: dict | None = None
    ) -> NodeProcess:
        log = self._log_path(f"runner-{node_name or 'node'}")
        r = NodeProcess(domain_id, log, plugin=plugin, node_name=node_name, params=params)
        self._pgids.append(r.pgid)
        self._runners.append(r)
        return r

    def stop_runner(self, r: NodeProcess) -> int:
        code = r.stop()
        if r in self._runners:
            self._runners.remove(r)
        return code

    def discovery_server(self) -> DiscoveryServer:
        """A discovery server (bench.discovery_server) until :meth:`close`."""
        lease = self.lease()
        server = DiscoveryServer(lease.domain_id, self._log_path("discovery-server"))
        self._pgids.append(server.pgid)
        self._servers.append(server)
        return server

    def core_worker(self, what: str, n: int, timeout: float = 600.0) -> dict:
        """Run ``python -m cloneguard.bench._core_worker`` (its own CloneCore) and return its JSON."""
        log = self._log_path(f"core-worker-{what}")
        with open(log, "wb") as err:
            done = subprocess.run(
                [sys.executable, "-m", "cloneguard.bench._core_worker", what, "--n", str(n)],
                cwd=REPO_ROOT,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=err,
                timeout=timeout,
                check=False,
            )
        if done.returncode != 0:
            raise RuntimeError(
                f"cloneguard.bench._core_worker {what} exited with {done.returncode}\n"
                + log_tail(log.read_text(errors="replace"))
            )
        return json.loads(done.stdout)

    def close(self) -> list[str]:
        """Stop everything still running; return what was left behind."""
        if self.closed:
            return []
        self.closed = True
        for running in list(self._running):
            try:
                self.stop(running)
            except Exception as exc:  # keep stopping the rest
                print(f"bench: stopping {running.label}: {exc}", file=sys.stderr)
        for r in list(self._runners):
            self.stop_runner(r)
        for server in self._servers:
            try:
                server.stop()
            except Exception as exc:  # keep stopping the rest
                print(f"bench: stopping the discovery server: {exc}", file=sys.stderr)
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
