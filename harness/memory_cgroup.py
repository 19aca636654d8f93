"""A memory cgroup of the harness's own making, with a limit, for a
container whose nodes may run out of memory: whatever they do, the machine
keeps the rest of its memory.

Made under the harness's own memory cgroup (so that any limit around the
harness holds too): cgroup v1's ``memory`` hierarchy (``memory.limit_in_bytes``,
swap held to the same limit where the kernel accounts it), else cgroup2
with the memory controller enabled for the harness's cgroup's children
(``memory.max``, ``memory.swap.max`` 0). The container is born in it (a
shell moves itself in, then execs it: process.py), so that nothing it
allocates is charged elsewhere. ``close`` removes it once its processes are
gone. Where neither can be made, ``MemoryCgroupUnavailable`` says why.
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path

from .cgroup_fs import cgroup_of, mounts, remove

#: how long a cgroup whose last task has just gone may stay busy
RMDIR_BUSY_S = 5.0
_names = itertools.count(1)


class MemoryCgroupUnavailable(RuntimeError):
    """No memory controller this harness can use here: the message says why."""


def _own(kind: str) -> str:
    """This process's cgroup path in that hierarchy ("/" for the root)."""
    path = cgroup_of("self", kind, "memory")
    if path is None:
        raise MemoryCgroupUnavailable(f"this process is in no {kind} memory cgroup (/proc/self/cgroup)")
    return path


def _parent() -> tuple[str, Path]:
    """("v1" or "v2", the directory the new cgroup goes in)."""
    for point, fstype, opts in mounts():
        if fstype == "cgroup" and "memory" in opts:
            return "v1", Path(point) / _own("v1").lstrip("/")
    for point, fstype, _ in mounts():
        if fstype == "cgroup2":
            parent = Path(point) / _own("v2").lstrip("/")
            try:
                enabled = (parent / "cgroup.subtree_control").read_text().split()
            except OSError:
                enabled = []
            if "memory" in enabled:
                return "v2", parent
            raise MemoryCgroupUnavailable(
                f"cgroup2 at {parent} does not enable the memory controller for its children "
                f"(cgroup.subtree_control: {' '.join(enabled) or 'empty'}) and there is no cgroup v1 memory hierarchy"
            )
    raise MemoryCgroupUnavailable("no cgroup v1 memory hierarchy and no cgroup2 mount")


class MemoryCgroup:
    """``MemoryCgroup(limit_bytes)``: made at once; ``procs`` is the file a
    process writes its pid to, to be in it."""

    def __init__(self, limit_bytes: int):
        if limit_bytes < (16 << 20):
            raise ValueError(f"a memory cgroup's limit is at least 16 MiB, not {limit_bytes} bytes")
        self.limit = limit_bytes
        self.kind, parent = _parent()
        self.dir = parent / f"cloneguard-harness-mem-{os.getpid()}-{next(_names)}"
        try:
            self.dir.mkdir()
        except OSError as exc:
            raise MemoryCgroupUnavailable(f"cannot make a cgroup in {parent}: {exc}") from None
        try:
            if self.kind == "v1":
                (self.dir / "memory.limit_in_bytes").write_text(str(limit_bytes))
                swap = self.dir / "memory.memsw.limit_in_bytes"
                if swap.exists():
                    swap.write_text(str(limit_bytes))
            else:
                (self.dir / "memory.max").write_text(str(limit_bytes))
                swap = self.dir / "memory.swap.max"
                if swap.exists():
                    swap.write_text("0")
        except BaseException:
            self.close()
            raise
        self.procs = self.dir / "cgroup.procs"

    def usage(self) -> int:
        """Bytes charged to it now."""
        name = "memory.usage_in_bytes" if self.kind == "v1" else "memory.current"
        return int((self.dir / name).read_text())

    def oom_kills(self) -> int:
        """Processes the kernel's OOM killer ended in it so far (0 where the
        kernel does not say: v1 before Linux 4.13)."""
        name = "memory.oom_control" if self.kind == "v1" else "memory.events"
        for line in (self.dir / name).read_text().splitlines():
            key, _, value = line.partition(" ")
            if key == "oom_kill":
                return int(value)
        return 0

    def close(self) -> None:
        """Removed, once the processes that were in it are gone."""
        remove(self.dir, RMDIR_BUSY_S, 0.05)
