"""Fast DDS shared-memory segments in /dev/shm, and which of them are orphans.

Fast DDS names a participant's segment ``fastrtps_<16 hex>`` and a port
``fastrtps_port<N>``; each has a lock file beside it (``<name>_el`` or
``<name>_sl``) that its owner holds an flock on while it is alive, and a
port also has a named semaphore ``sem.fastrtps_port<N>_mutex``. A segment
whose lock file can be flocked exclusively has no live owner: it is an
orphan (this is how Fast DDS's own ``shm clean`` tells them apart).

The harness only ever removes orphans among the names that appeared while
it ran something of its own: never anyone else's segment, live or dead.
"""
from __future__ import annotations

import fcntl
import os
import re
from dataclasses import dataclass
from pathlib import Path

SHM_DIR = Path("/dev/shm")
PREFIX = "fastrtps_"
_LOCK = re.compile(r"^(fastrtps_(?:[0-9a-f]{16}|port\d{1,5}))_(el|sl)$")


def segments() -> set[str]:
    """Names of the Fast DDS files (segments, lock files, port semaphores) present now."""
    try:
        return {p.name for p in SHM_DIR.iterdir() if p.name.startswith(PREFIX) or p.name.startswith("sem." + PREFIX)}
    except FileNotFoundError:
        return set()


@dataclass(frozen=True)
class Segment:
    name: str             # fastrtps_<hash> or fastrtps_port<N>
    files: tuple[str, ...]  # every file that belongs to it and exists
    orphan: bool


def _take_lock(path: Path) -> int | None:
    """An fd holding an exclusive flock on ``path``, or None if it is held."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def _lock_is_free(path: Path) -> bool:
    fd = _take_lock(path)
    if fd is None:
        return False
    os.close(fd)
    return True


def classify(names: set[str]) -> list[Segment]:
    """Group ``names`` into segments and tell which are orphans."""
    found = []
    for name in sorted(names):
        m = _LOCK.match(name)
        if not m:
            continue
        base = m.group(1)
        files = [name, base]
        if "port" in base:
            files.append(f"sem.{base}_mutex")
        present = tuple(f for f in files if (SHM_DIR / f).exists())
        found.append(Segment(base, present, _lock_is_free(SHM_DIR / name)))
    return found


def remove_orphans(names: set[str]) -> list[Segment]:
    """Remove the orphaned segments among ``names``; return what was removed."""
    removed = []
    for seg in classify(names):
        if not seg.orphan:
            continue
        # Hold the lock while unlinking, so nobody can start using it meanwhile.
        fd = _take_lock(SHM_DIR / seg.files[0])
        if fd is None:
            continue
        try:
            for f in seg.files:
                try:
                    (SHM_DIR / f).unlink()
                except FileNotFoundError:
                    pass
        finally:
            os.close(fd)
        removed.append(seg)
    return removed


def mapped_by(pid: int) -> set[str]:
    """Names of the Fast DDS segments process ``pid`` has mapped."""
    try:
        with open(f"/proc/{pid}/maps") as f:
            maps = f.read()
    except (FileNotFoundError, ProcessLookupError):
        return set()
    return set(re.findall(r"/dev/shm/(fastrtps_[0-9a-z]+)", maps))


def remove_orphans_of(names: set[str], owners: set[str]) -> list[Segment]:
    """Like :func:`remove_orphans`, limited to segments in ``owners`` (segment
    names a process of ours was seen to map): never anyone else's orphans."""
    return remove_orphans({n for n in names if _base(n) in owners})


def _base(name: str) -> str:
    m = _LOCK.match(name)
    if m:
        return m.group(1)
    return re.sub(r"^sem\.|_mutex$", "", name)
