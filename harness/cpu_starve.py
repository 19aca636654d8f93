"""CPU starvation of one process from outside: for a while, the process
runs in a cgroup of the harness's own with a CPU quota, then goes back to
the cgroup it came from and the harness's cgroup is removed.

Black-box: it reads ``/proc/<pid>/cgroup`` and writes cgroup files, never
the container's state. Where the cpu controller is (mounts, as the
container's cgroups.py finds them): cgroup v1's ``cpu`` hierarchy
(``cpu.cfs_quota_us`` over ``cpu.cfs_period_us``), else cgroup2 with
``cpu`` enabled for its root's children (``cpu.max``). With neither, or
without the right to make a cgroup, ``CpuStarveUnavailable`` says why.

A quota is CPUs: 0.5 is half of one core; the smallest is 1 ms a second
(0.001). The period is one second below 0.01 CPUs (the kernel's smallest
quota is 1 ms), 100 ms otherwise.
"""

from __future__ import annotations

import errno
import itertools
import os
from pathlib import Path

from .cgroup_fs import cgroup_of, mounts, remove

#: how long a cgroup that its last task has just left may stay busy
RMDIR_BUSY_S = 1.0
_names = itertools.count(1)


class CpuStarveUnavailable(RuntimeError):
    """No cpu controller this harness can use here: the message says why."""


def _hierarchy() -> tuple[str, Path]:
    """("v1", cpu mount) or ("v2", cgroup2 mount with cpu for children)."""
    for point, fstype, opts in mounts():
        if fstype == "cgroup" and "cpu" in opts:
            return "v1", Path(point)
    for point, fstype, _ in mounts():
        if fstype == "cgroup2":
            try:
                enabled = (Path(point) / "cgroup.subtree_control").read_text().split()
            except OSError:
                enabled = []
            if "cpu" in enabled:
                return "v2", Path(point)
            raise CpuStarveUnavailable(
                f"cgroup2 at {point} has no cpu controller for its children (cgroup.subtree_control: "
                f"{' '.join(enabled) or 'empty'}) and there is no cgroup v1 cpu hierarchy"
            )
    raise CpuStarveUnavailable("no cgroup v1 cpu hierarchy and no cgroup2 mount")


def _current(pid: int, kind: str) -> str:
    """The process's cgroup path in that hierarchy ("/" for the root)."""
    path = cgroup_of(pid, kind, "cpu")
    if path is not None:
        return path
    raise CpuStarveUnavailable(f"pid {pid} is in no {kind} cpu cgroup (/proc/{pid}/cgroup)")


def quota_and_period(cpus: float) -> tuple[int, int]:
    """(quota, period) in microseconds for ``cpus`` CPUs."""
    if not 0.001 <= cpus <= 1024:
        raise ValueError(f"a CPU quota is 0.001-1024 CPUs, not {cpus!r}")
    period = 1_000_000 if cpus < 0.01 else 100_000
    return max(1000, round(cpus * period)), period


class CpuStarve:
    """``with CpuStarve(pid, cpus):`` the process held to ``cpus`` CPUs."""

    def __init__(self, pid: int, cpus: float):
        self.pid = pid
        self.quota, self.period = quota_and_period(cpus)
        self.kind, self.mount = _hierarchy()
        self.dir = self.mount / f"cloneguard-harness-{os.getpid()}-{next(_names)}"
        self._home: Path | None = None

    def __enter__(self) -> CpuStarve:
        self._home = self.mount / _current(self.pid, self.kind).lstrip("/")
        try:
            self.dir.mkdir()
        except PermissionError as exc:
            raise CpuStarveUnavailable(f"cannot make a cgroup in {self.mount}: {exc}") from None
        try:
            if self.kind == "v1":
                (self.dir / "cpu.cfs_period_us").write_text(str(self.period))
                (self.dir / "cpu.cfs_quota_us").write_text(str(self.quota))
            else:
                (self.dir / "cpu.max").write_text(f"{self.quota} {self.period}")
            (self.dir / "cgroup.procs").write_text(str(self.pid))
        except BaseException:
            self._remove()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            if self._home is not None:
                (self._home / "cgroup.procs").write_text(str(self.pid))
        except ProcessLookupError:
            pass  # it died meanwhile: nothing to move back
        except OSError as err:
            if err.errno not in (errno.ESRCH, errno.ENOENT):
                raise
        finally:
            self._remove()

    def _remove(self) -> None:
        remove(self.dir, RMDIR_BUSY_S, 0.01)
