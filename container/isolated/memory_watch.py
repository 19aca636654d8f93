"""What memory the container may use, for its memory watch (memwatch.c),
which ends the node process that uses the most before the container's use
reaches it: the kernel's OOM killer would end every process that shares the
address space, the whole container.

Found at start-up, the nearest limit (the smallest over the container's
cgroup and its ancestors, where the kernel's OOM killer would act):

* cgroup2: ``memory.max`` and ``memory.high`` (above ``high`` the kernel
  throttles the cgroup and reclaims hard); use: ``memory.current`` less
  ``inactive_file`` of ``memory.stat``;
* cgroup v1's memory hierarchy: ``memory.limit_in_bytes``; use:
  ``memory.usage_in_bytes`` less ``total_inactive_file``;
* neither limited: the machine, ``MemTotal``; use: ``MemTotal`` less
  ``MemAvailable`` (/proc/meminfo).

The margin is how far below the limit the watch acts: at least
``MIN_MARGIN``, and ``MARGIN_SHARE`` of the limit. The watch looks often
enough near the limit to win against a node allocating 4 GiB/s
(memwatch.c); bench.memory_watch measures the margin it needs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .cgroups import cgroup2_mount, own_cgroup, v1_mount

MIN_MARGIN = 64 << 20
MARGIN_SHARE = 0.02
_NO_LIMIT = 1 << 60  # cgroup v1 writes "no limit" as the largest page count


@dataclass(frozen=True)
class MemoryLimit:
    limit: int  # bytes the container may use
    where: str  # what says so, for the log
    usage: str  # the file whose first number is the use (or /proc/meminfo)
    stat: str | None = None  # memory.stat, for its inactive file cache
    stat_key: str = ""
    meminfo: bool = False

    def margin(self, asked: int | None = None) -> int:
        return asked if asked is not None else max(MIN_MARGIN, int(self.limit * MARGIN_SHARE))


def _number(path: Path) -> int | None:
    try:
        text = path.read_text().split()[0]
    except (OSError, IndexError):
        return None
    return None if text == "max" else int(text)


def _ancestors(root: Path, own: str) -> list[Path]:
    """The cgroup's directory and each parent's up to the root, nearest first."""
    parts = [p for p in own.split("/") if p]
    return [root.joinpath(*parts[:n]) for n in range(len(parts), -1, -1)]


def _smallest(dirs: list[Path], files: tuple[str, ...]) -> tuple[int, Path, str] | None:
    found = [(n, d, name) for d in dirs for name in files if (n := _number(d / name)) is not None and n < _NO_LIMIT]
    return min(found, key=lambda f: f[0]) if found else None


def _meminfo() -> dict[str, int]:
    with open("/proc/meminfo") as f:
        return {k: int(v.split()[0]) * 1024 for k, v in (line.split(":", 1) for line in f)}


def find() -> MemoryLimit:
    """The container's nearest memory limit (see the module)."""
    v2 = cgroup2_mount()
    if v2 is not None and (v2 / "cgroup.controllers").exists():
        dirs = _ancestors(v2, own_cgroup(""))
        hit = _smallest([d for d in dirs if (d / "memory.current").exists()], ("memory.max", "memory.high"))
        if hit is not None:
            limit, where, name = hit
            return MemoryLimit(limit, f"cgroup2 {name} of {where}", str(where / "memory.current"),
                               str(where / "memory.stat"), "inactive_file")  # fmt: skip
    v1 = v1_mount("memory")
    if v1 is not None:
        hit = _smallest(_ancestors(v1, own_cgroup("memory")), ("memory.limit_in_bytes",))
        if hit is not None:
            limit, where, name = hit
            return MemoryLimit(limit, f"cgroup v1 {name} of {where}", str(where / "memory.usage_in_bytes"),
                               str(where / "memory.stat"), "total_inactive_file")  # fmt: skip
    return MemoryLimit(_meminfo()["MemTotal"], "the machine's memory (MemTotal)", "/proc/meminfo", meminfo=True)


def open_files(limit: MemoryLimit) -> tuple[int, int]:
    """The usage file and memory.stat (-1: none), open for the monitor."""
    usage = os.open(limit.usage, os.O_RDONLY | os.O_CLOEXEC)
    stat = os.open(limit.stat, os.O_RDONLY | os.O_CLOEXEC) if limit.stat else -1
    return usage, stat
