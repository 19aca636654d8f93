"""Per-node cgroups: each node's process is born in a cgroup of its own.

The child is placed at birth with clone3(CLONE_INTO_CGROUP), which takes a
cgroup2 directory fd, so there is no moment where it runs elsewhere. A CPU
quota goes where a cpu controller is: the cgroup2 directory's ``cpu.max``
when cgroup2 has the controller, else the cgroup v1 ``cpu`` hierarchy
(``cpu.cfs_quota_us``; on a hybrid machine such as Debian 12 with v1
controllers, the v2 tree has none). A v1 group cannot be entered at birth:
the pid is written to it right after the clone.

Layout, all removed when the node or the container goes:
    <cgroup2 mount>/cloneguard-<container pid>/node-<unique_id>
    <v1 cpu mount>/cloneguard-<container pid>/node-<unique_id>   (quota only)

A container that ends without its shutdown (SIGKILL, the watchdog's exit)
cannot remove them: its cgroup janitor (cgroup_janitor.py, a process of its
own started with the roots) does, once the container and its node processes
are gone.
"""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from typing import IO

CFS_PERIOD_US = 100_000


class CgroupsUnavailable(RuntimeError):
    pass


def _mounts() -> list[tuple[str, str, str]]:
    """(mount point, fstype, options) of every mount."""
    out = []
    with open("/proc/self/mounts") as f:
        for line in f:
            parts = line.split()
            if len(parts) >= 4:
                out.append((parts[1], parts[2], parts[3]))
    return out


def cgroup2_mount() -> Path | None:
    for point, fstype, _opts in _mounts():
        if fstype == "cgroup2":
            return Path(point)
    return None


def v1_mount(controller: str) -> Path | None:
    """Where cgroup v1's hierarchy with that controller is mounted."""
    for point, fstype, opts in _mounts():
        if fstype == "cgroup" and controller in opts.split(","):
            return Path(point)
    return None


def v1_cpu_mount() -> Path | None:
    return v1_mount("cpu")


def own_cgroup(hierarchy: str) -> str:
    """This process's cgroup path in a hierarchy: a v1 controller's name, or
    "" for cgroup2 (/proc/self/cgroup); "/" when it is not listed."""
    with open("/proc/self/cgroup") as f:
        for line in f:
            _id, controllers, path = line.rstrip("\n").split(":", 2)
            names = controllers.split(",") if controllers else []
            if (hierarchy in names) if hierarchy else not names:
                return path
    return "/"


@dataclass
class NodeCgroup:
    unique_id: int
    v2_dir: Path
    fd: int  # open cgroup2 dir, for CLONE_INTO_CGROUP
    cpu_v1_dir: Path | None = None


def _rmdir(path: Path, timeout: float = 1.0) -> None:
    """rmdir a cgroup; it can be briefly busy while the kernel lets a dead
    task go, so EBUSY is retried for up to ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            path.rmdir()
            return
        except FileNotFoundError:
            return
        except OSError as exc:
            if exc.errno != errno.EBUSY or time.monotonic() >= deadline:
                raise
            time.sleep(0.005)


class NodeCgroups:
    def __init__(self, name: str | None = None):
        v2 = cgroup2_mount()
        if v2 is None:
            raise CgroupsUnavailable("no cgroup2 hierarchy is mounted (needed for CLONE_INTO_CGROUP)")
        self.name = name or f"cloneguard-{os.getpid()}"
        self.v2_root = v2 / self.name
        controllers = (v2 / "cgroup.controllers").read_text().split()
        self._v2_cpu = "cpu" in controllers
        self._v1_cpu = None if self._v2_cpu else v1_cpu_mount()
        self.v1_root = self._v1_cpu / self.name if self._v1_cpu else None
        # A container that was SIGKILLed could not remove its cgroups; one
        # that had our pid left them under our name.
        self.reclaimed = self._reclaim_stale()
        try:
            self.v2_root.mkdir(exist_ok=False)
        except OSError as exc:
            raise CgroupsUnavailable(f"cannot create {self.v2_root}: {exc.strerror}") from None
        if self._v2_cpu:
            (v2 / "cgroup.subtree_control").write_text("+cpu")
            (self.v2_root / "cgroup.subtree_control").write_text("+cpu")
        self._janitor_pipe = self._start_janitor()

    def _start_janitor(self) -> IO[bytes]:
        """Start the process that removes our cgroups if we end without
        close() (cgroup_janitor.py); the write end of the pipe whose end of
        file it waits for, which only this process holds."""
        roots = [str(r) for r in (self.v2_root, self.v1_root) if r is not None]
        script = Path(__file__).with_name("cgroup_janitor.py")
        try:
            first = subprocess.Popen(
                [sys.executable, "-I", "-S", str(script), str(os.getpid()), *roots],
                stdin=subprocess.PIPE,
                stdout=subprocess.DEVNULL,
                start_new_session=True,
            )
            first.wait(10)  # it forks the janitor and exits
        except (OSError, subprocess.TimeoutExpired) as exc:
            _rmdir(self.v2_root)
            raise CgroupsUnavailable(f"cannot start the cgroup janitor: {exc}") from None
        return first.stdin  # type: ignore[return-value]  # stdin=PIPE: never None

    def _reclaim_stale(self) -> list[str]:
        """Remove cgroups already named for us that no process is in (left
        by a dead container that had our pid); refuse, naming them, if a
        process is in one. Returns the removed roots."""
        removed = []
        for root in (self.v2_root, self.v1_root):
            if root is None or not root.is_dir():
                continue
            tree = sorted((d for d in root.rglob("*") if d.is_dir()), key=lambda d: len(d.parts), reverse=True) + [root]
            busy = [str(d) for d in tree if (d / "cgroup.procs").read_text().strip()]
            if busy:
                raise CgroupsUnavailable(f"{root} already exists and has processes in {busy}")
            try:
                for d in tree:
                    _rmdir(d)
            except OSError as exc:
                raise CgroupsUnavailable(f"cannot remove the stale cgroup {root}: {exc.strerror}") from None
            removed.append(str(root))
        return removed

    def cpu_quota_supported(self) -> bool:
        return self._v2_cpu or self._v1_cpu is not None

    def create(self, unique_id: int, cpu_quota: float | None = None) -> NodeCgroup:
        """A cgroup for one node; ``cpu_quota`` in CPUs (0.5 = half a core)."""
        if cpu_quota is not None and not self.cpu_quota_supported():
            raise CgroupsUnavailable("no cpu controller is available for a CPU quota")
        v2_dir = self.v2_root / f"node-{unique_id}"
        v2_dir.mkdir()
        cg = NodeCgroup(unique_id, v2_dir, os.open(v2_dir, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC))
        try:
            self._set_quota(cg, cpu_quota)
        except BaseException:
            self.remove(cg)  # nothing may stay of a cgroup that failed
            raise
        return cg

    def _set_quota(self, cg: NodeCgroup, cpu_quota: float | None) -> None:
        unique_id, v2_dir = cg.unique_id, cg.v2_dir
        if cpu_quota is not None:
            quota_us = max(1000, int(cpu_quota * CFS_PERIOD_US))
            if self._v2_cpu:
                (v2_dir / "cpu.max").write_text(f"{quota_us} {CFS_PERIOD_US}")
            else:
                assert self.v1_root is not None, "without a v2 cpu controller NodeCgroups needs v1's"
                self.v1_root.mkdir(exist_ok=True)
                cg.cpu_v1_dir = self.v1_root / f"node-{unique_id}"
                cg.cpu_v1_dir.mkdir()
                (cg.cpu_v1_dir / "cpu.cfs_period_us").write_text(str(CFS_PERIOD_US))
                (cg.cpu_v1_dir / "cpu.cfs_quota_us").write_text(str(quota_us))

    def unthrottle(self, cg: NodeCgroup) -> None:
        """Lift a node's CPU quota, so that it winds down at full speed when
        it is asked to stop (at 0.01 CPUs its clean stop takes seconds, and
        a node killed for being slow leaves its participant behind)."""
        try:
            if cg.cpu_v1_dir is not None:
                (cg.cpu_v1_dir / "cpu.cfs_quota_us").write_text("-1")
            elif self._v2_cpu:
                (cg.v2_dir / "cpu.max").write_text(f"max {CFS_PERIOD_US}")
        except OSError:
            pass  # then it stops throttled: slower, not wrong

    def attach(self, cg: NodeCgroup, pid: int) -> None:
        """After the clone: join the v1 cpu group, if the node has one."""
        if cg.cpu_v1_dir is not None:
            (cg.cpu_v1_dir / "cgroup.procs").write_text(str(pid))

    def remove(self, cg: NodeCgroup) -> None:
        """Once the node's process is gone."""
        os.close(cg.fd)
        _rmdir(cg.v2_dir)
        if cg.cpu_v1_dir is not None:
            _rmdir(cg.cpu_v1_dir)

    def close(self) -> list[str]:
        """Remove every cgroup this container made, emptying any that still
        holds a process first (cgroup.kill), then let the janitor go. Never
        raises: returns what could not be removed."""
        problems = self._remove_all()
        self._janitor_pipe.close()  # the janitor finds nothing left and ends
        return problems

    def _remove_all(self) -> list[str]:
        problems = []
        for root in (self.v2_root, self.v1_root):
            if root is None or not root.exists():
                continue
            for d in sorted(root.glob("node-*")):
                if root == self.v2_root and (d / "cgroup.kill").exists():
                    try:
                        (d / "cgroup.kill").write_text("1")
                    except OSError as exc:
                        problems.append(f"{d}/cgroup.kill: {exc.strerror}")
                try:
                    _rmdir(d)
                except OSError as exc:
                    problems.append(f"{d}: {exc.strerror}")
            try:
                _rmdir(root)
            except OSError as exc:
                problems.append(f"{root}: {exc.strerror}")
        return problems
