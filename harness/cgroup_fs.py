"""What the harness's own cgroups (cpu_starve.py, memory_cgroup.py) share:
where the hierarchies are mounted, which cgroup a process is in, and the
removal of a cgroup the kernel may keep busy a moment after its last task."""

from __future__ import annotations

import errno
import time
from pathlib import Path


def mounts() -> list[tuple[str, str, list[str]]]:
    """(mount point, fstype, options) of every mount."""
    with open("/proc/self/mounts") as f:
        return [(p[1], p[2], p[3].split(",")) for p in (line.split() for line in f) if len(p) >= 4]


def cgroup_of(pid: int | str, kind: str, controller: str) -> str | None:
    """Process ``pid``'s ("self" for this one) cgroup path in cgroup v1's
    ``controller`` hierarchy (``kind`` "v1") or in cgroup2 ("v2"); None if
    it is in none."""
    with open(f"/proc/{pid}/cgroup") as f:
        for line in f:
            _, controllers, path = line.rstrip("\n").split(":", 2)
            if (kind == "v1" and controller in controllers.split(",")) or (kind == "v2" and controllers == ""):
                return path
    return None


def remove(path: Path, busy_s: float, pause_s: float) -> None:
    """rmdir a cgroup (gone already is fine). EBUSY, while the kernel still
    lets a task that left or died go, is tried again for ``busy_s``."""
    deadline = time.monotonic() + busy_s
    while True:
        try:
            path.rmdir()
            return
        except FileNotFoundError:
            return
        except OSError as err:
            if err.errno != errno.EBUSY or time.monotonic() > deadline:
                raise
            time.sleep(pause_s)
