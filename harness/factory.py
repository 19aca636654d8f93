"""Containers and clients started together, stopped together.

Used by the pytest fixtures (one factory per test) and by the standalone
commands (``python -m cloneguard.harness reproduce``): every container it starts and
every client it connects is closed by :meth:`stop_all`, and only those.
"""

from __future__ import annotations

import os
import re
from collections.abc import Sequence
from pathlib import Path

from .client import ContainerClient
from .memory_cgroup import MemoryCgroup
from .process import NO_SHM_PROFILE, ContainerProcess, ExitStatus

#: how long a started container may take to answer ListNodes; a slower
#: machine (an emulated CPU: scripts/pku_vm.sh) sets CLONEGUARD_READY_TIMEOUT
READY_TIMEOUT_S = float(os.environ.get("CLONEGUARD_READY_TIMEOUT", "20"))


# Where a container's log has every thread's stack: its watchdog's banner
# (docs/options.md, --watchdog), or faulthandler's, whose C thread dumps
# them when no Python thread can run.
_STACKS_BANNER = re.compile(r"^(cloneguard watchdog: .*the stacks of all threads follow|Timeout \(\d+:\d\d:\d\d\)!)")
STACKS_MAX_LINES = 600


def log_tail(text: str, lines: int = 60) -> str:
    """The log's last ``lines`` lines; if it holds a dump of every thread's
    stack, from that dump's banner on instead (at most STACKS_MAX_LINES), as
    the thread that explains a hang is seldom among the last lines."""
    all_lines = text.splitlines()
    start = len(all_lines) - lines
    for i in range(len(all_lines) - 1, -1, -1):
        if _STACKS_BANNER.match(all_lines[i]):
            start = min(start, max(i, len(all_lines) - STACKS_MAX_LINES))
            break
    return "\n".join(all_lines[max(start, 0) :])


def wait_ready(cli: ContainerClient, proc: ContainerProcess, timeout: float = READY_TIMEOUT_S) -> None:
    """Wait until the container answers ListNodes (its services are up)."""
    try:
        cli.list(timeout=timeout)
    except AssertionError as exc:
        state = "running" if proc.alive() else f"exited with {proc.wait(0)}"
        raise AssertionError(
            f"container not ready ({state}): {exc}\n--- log ---\n{log_tail(proc.log_text())}"
        ) from None


class ContainerFactory:
    def __init__(self, domain_id: int, log_dir: Path, *, exe: str | None = None):
        self.domain_id = domain_id
        self._log_dir = Path(log_dir)
        self._exe = exe
        self.started: list[ContainerProcess] = []
        self.clients: list[ContainerClient] = []

    def start(
        self,
        args: Sequence[str] = (),
        *,
        node_name: str = "ComponentManager",
        fastdds_profile: Path = NO_SHM_PROFILE,
        extra_env: dict[str, str] | None = None,
        exe: str | None = None,
        memory_limit: int | None = None,
    ) -> ContainerProcess:
        """``exe`` overrides the factory's container executable for this one;
        with ``memory_limit`` (bytes) it runs in a memory cgroup of the
        harness's own making with that limit (memory_cgroup.py; where none
        can be made, MemoryCgroupUnavailable says why)."""
        cgroup = MemoryCgroup(memory_limit) if memory_limit is not None else None
        try:
            proc = ContainerProcess(
                list(args),
                domain_id=self.domain_id,
                log_path=self._log_dir / f"container-{len(self.started)}.log",
                exe=exe or self._exe,
                node_name=node_name,
                fastdds_profile=fastdds_profile,
                extra_env=extra_env,
                memory_cgroup=cgroup,
            )
        except BaseException:
            if cgroup is not None:
                cgroup.close()
            raise
        self.started.append(proc)
        return proc

    def connect(self, proc: ContainerProcess, fqn: str | None = None) -> ContainerClient:
        """A client of ``proc``, returned once the container answers."""
        cli = ContainerClient(proc.domain_id, fqn or proc.fqn)
        self.clients.append(cli)
        wait_ready(cli, proc)
        return cli

    def disconnect(self, cli: ContainerClient) -> None:
        """Close ``cli`` (a client of a container that is gone) now, not at
        stop_all: each is a DDS participant of this process."""
        cli.close()
        self.clients.remove(cli)

    def stop_all(self) -> list[ExitStatus]:
        for cli in self.clients:
            cli.close()
        return [proc.stop() for proc in self.started]
