"""Fast DDS shared-memory segments in /dev/shm, and which of them are orphans.

Fast DDS names a participant's segment ``fastrtps_<16 hex>`` and a port
``fastrtps_port<N>``; each has a lock file beside it (``<name>_el`` or
``<name>_sl``) that its owner holds an flock on while it is alive, and a
port also has a named semaphore ``sem.fastrtps_port<N>_mutex`` (the mutex
Fast DDS holds while it opens, creates or removes the port). A segment
whose lock file can be flocked exclusively has no live owner: it is an
orphan (this is how Fast DDS's own ``shm clean`` tells them apart).

Fast DDS also leaves *lock-less* ports: a port file and its semaphore with
no lock file at all (Fast DDS 2.14; seen in the SIGKILL scenario):

* a participant's own port that a SIGKILLed peer had opened to send to: the
  dead peer's reference in the port's count never goes, so when the owner
  stops gracefully it removes its lock file but leaves the segment;
* a dead participant's port that a live peer sends to: the peer finds its
  lock free, removes the port and its lock file and makes a new port (a
  sender's, with no lock file), or makes one where the harness removed it,
  and leaves it behind when it stops.

Nobody owns such a port, so no lock can tell. A lock-less port is an orphan
when no live process maps it or its semaphore (whoever uses a port maps it,
and whoever opens one maps the semaphore first); it is removed while
holding Fast DDS's own mutex of the port, so nobody can start opening it
meanwhile (Fast DDS removes a port under that mutex too).

The harness only ever removes orphans among the names that appeared while
it ran something of its own: never anyone else's segment, live or dead.
Every function takes the directory to look in (``shm_dir``, default
:data:`SHM_DIR`), so the rules can be exercised on files made elsewhere.
"""

from __future__ import annotations

import ctypes
import errno
import fcntl
import os
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

SHM_DIR = Path("/dev/shm")
PREFIX = "fastrtps_"
_LOCK_KINDS = ("el", "sl")
_LOCK = re.compile(r"^(fastrtps_(?:[0-9a-f]{16}|port\d{1,5}))_(el|sl)$")
_SEGMENT = re.compile(r"^fastrtps_(?:[0-9a-f]{16}|port\d{1,5})$")
_PORT = re.compile(r"^fastrtps_port\d{1,5}$")
_SEM = re.compile(r"^sem\.(fastrtps_port\d{1,5})_mutex$")
# glibc keeps named semaphores here, whatever directory is being examined.
_GLIBC_SEM_DIR = Path("/dev/shm")

FileId = tuple[int, int]  # (st_dev, st_ino)


def _dir(shm_dir: Path | str | None) -> Path:
    return SHM_DIR if shm_dir is None else Path(shm_dir)


def segments(shm_dir: Path | str | None = None) -> set[str]:
    """Names of the Fast DDS files (segments, lock files, port semaphores) present now."""
    try:
        return {
            p.name for p in _dir(shm_dir).iterdir() if p.name.startswith(PREFIX) or p.name.startswith("sem." + PREFIX)
        }
    except FileNotFoundError:
        return set()


@dataclass(frozen=True)
class Segment:
    name: str  # fastrtps_<hash> or fastrtps_port<N>
    files: tuple[str, ...]  # every file that belongs to it and exists
    orphan: bool
    lockless: bool = False  # a port with no lock file (see the module docstring)


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


def _file_id(path: Path) -> FileId | None:
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    return (st.st_dev, st.st_ino)


def mapped_files(discount: FileId | None = None) -> set[FileId]:
    """(device, inode) of every file some live process has mapped now.

    By inode, not by name: a process still mapping an unlinked file of the
    same name does not make a newer file of that name in use. ``discount``
    is a file this process maps only to hold a lock, not counted for it.
    Processes whose maps cannot be read (other users') are not counted: they
    cannot open our files for writing, as Fast DDS must."""
    me = os.getpid()
    found: set[FileId] = set()
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        pid = int(entry)
        try:
            with open(f"/proc/{pid}/maps") as f:
                lines = f.readlines()
        except OSError:
            continue
        for line in lines:
            # start-end perms offset major:minor inode [path]
            fields = line.split(maxsplit=5)
            if len(fields) < 5 or fields[4] == "0":
                continue
            major, _, minor = fields[3].partition(":")
            fid = (os.makedev(int(major, 16), int(minor, 16)), int(fields[4]))
            if pid == me and fid == discount:
                continue
            found.add(fid)
    return found


def _base(name: str) -> str:
    m = _LOCK.match(name)
    if m:
        return m.group(1)
    m = _SEM.match(name)
    if m:
        return m.group(1)
    return name


def _files_of(base: str) -> list[str]:
    files = [*(f"{base}_{k}" for k in _LOCK_KINDS), base]
    if _PORT.match(base):
        files.append(f"sem.{base}_mutex")
    return files


def _lockless_in_use(d: Path, base: str, mapped: set[FileId]) -> bool:
    """Is a lock-less port mapped (the port or its semaphore) by a live process?"""
    return any((fid := _file_id(d / f)) is not None and fid in mapped for f in (base, f"sem.{base}_mutex"))


def classify(names: set[str], shm_dir: Path | str | None = None) -> list[Segment]:
    """Group ``names`` into segments and tell which are orphans.

    A segment with a lock file is an orphan when that lock is free; a port
    with no lock file (``lockless``) when no live process maps it or its
    semaphore. Names that are neither are ignored."""
    d = _dir(shm_dir)
    bases = sorted({b for b in map(_base, names) if _SEGMENT.match(b)})
    found = []
    mapped: set[FileId] | None = None
    for base in bases:
        present = tuple(f for f in _files_of(base) if (d / f).exists())
        if not present:
            continue
        locks = [f for f in present if f.endswith(("_el", "_sl"))]
        if locks:
            found.append(Segment(base, present, all(_lock_is_free(d / f) for f in locks)))
        elif _PORT.match(base):
            if mapped is None:
                mapped = mapped_files()
            found.append(Segment(base, present, not _lockless_in_use(d, base, mapped), lockless=True))
        # A participant segment without its lock file: its owner is between
        # creating the one and the other. Never ours to judge.
    return found


# -- Fast DDS's mutex of a port: a POSIX named semaphore -----------------------------------

_SEM_FAILED = None  # ctypes returns a NULL sem_t* as None
_libc = None


def _c() -> ctypes.CDLL:
    global _libc
    if _libc is None:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.sem_open.restype = ctypes.c_void_p
        libc.sem_open.argtypes = [ctypes.c_char_p, ctypes.c_int, ctypes.c_uint, ctypes.c_uint]
        for fn in (libc.sem_trywait, libc.sem_post, libc.sem_close):
            fn.argtypes = [ctypes.c_void_p]
            fn.restype = ctypes.c_int
        _libc = libc
    return _libc


@contextmanager
def _port_mutex(d: Path, base: str) -> Iterator[FileId | None]:
    """Hold Fast DDS's mutex of port ``base`` (``sem.<base>_mutex``) if it
    is free, the way Fast DDS holds it while it opens or removes the port:
    nobody can start opening the port meanwhile. Yields the semaphore file
    this process maps for it (not a sign of anyone else using the port), or
    None. If someone else holds it, it is not waited for: a live holder maps
    it, which the caller sees; a dead one never lets go.

    Only in glibc's semaphore directory: elsewhere there is no mutex to hold."""
    if d.resolve() != _GLIBC_SEM_DIR.resolve():
        yield None
        return
    libc = _c()
    name = f"/{base}_mutex".encode()
    # If there is no semaphore, make it, taken (value 0): an opener that
    # comes now waits for it instead of making its own.
    sem = libc.sem_open(name, os.O_CREAT | os.O_EXCL, 0o644, 0)
    taken = sem is not _SEM_FAILED
    if not taken:
        if ctypes.get_errno() != errno.EEXIST:
            yield None
            return
        sem = libc.sem_open(name, 0, 0, 0)
        if sem is _SEM_FAILED:  # removed between the two calls
            yield None
            return
        taken = libc.sem_trywait(sem) == 0
    try:
        yield _file_id(d / f"sem.{base}_mutex")
    finally:
        if taken:
            libc.sem_post(sem)
        libc.sem_close(sem)


def _remove_lockless(d: Path, base: str) -> bool:
    """Remove a lock-less port if, under its mutex, it still is an orphan."""
    with _port_mutex(d, base) as own:
        if any((d / f"{base}_{k}").exists() for k in _LOCK_KINDS):
            return False  # a listener has just opened it
        if _lockless_in_use(d, base, mapped_files(discount=own)):
            return False
        removed = False
        for f in (base, f"sem.{base}_mutex"):
            try:
                (d / f).unlink()
                removed = True
            except FileNotFoundError:
                pass
        return removed


def remove_orphans(names: set[str], shm_dir: Path | str | None = None) -> list[Segment]:
    """Remove the orphaned segments among ``names``; return what was removed."""
    d = _dir(shm_dir)
    removed = []
    for seg in classify(names, d):
        if not seg.orphan:
            continue
        if seg.lockless:
            if _remove_lockless(d, seg.name):
                removed.append(seg)
            continue
        # Hold the lock while unlinking, so nobody can start using it meanwhile.
        lock = next(f for f in seg.files if f.endswith(("_el", "_sl")))
        fd = _take_lock(d / lock)
        if fd is None:
            continue
        try:
            for f in seg.files:
                try:
                    (d / f).unlink()
                except FileNotFoundError:
                    pass
        finally:
            os.close(fd)
        removed.append(seg)
    return removed


def mapped_by(pid: int, shm_dir: Path | str | None = None) -> set[str]:
    """Names of the Fast DDS segments process ``pid`` has mapped."""
    try:
        with open(f"/proc/{pid}/maps") as f:
            maps = f.read()
    except (FileNotFoundError, ProcessLookupError):
        return set()
    where = re.escape(str(_dir(shm_dir)).rstrip("/"))
    return set(re.findall(where + r"/(fastrtps_[0-9a-z]+)", maps))


def locked_by(pids: set[int], shm_dir: Path | str | None = None) -> set[str]:
    """Segments whose lock file one of ``pids`` holds an exclusive flock on
    now (from /proc/locks, which names the process that took each lock): the
    segments and exclusive ports those processes own, not merely use. (Fast
    DDS's test of whether a port is a zombie takes its lock files for an
    instant: the exclusive one only when nobody owns the port, the shared
    one always. Shared locks are not counted.)"""
    d = _dir(shm_dir)
    bases: dict[FileId, str] = {}
    for name in segments(d):
        m = _LOCK.match(name)
        if m and (fid := _file_id(d / name)) is not None:
            bases[fid] = m.group(1)
    found: set = set()
    try:
        with open("/proc/locks") as f:
            lines = f.readlines()
    except FileNotFoundError:
        return found
    for line in lines:
        # "1: FLOCK  ADVISORY  WRITE 1234 00:1b:15087 0 EOF"; a waiter's line has "->" second
        fields = line.split()
        if len(fields) < 6 or fields[1] != "FLOCK" or fields[3] != "WRITE" or int(fields[4]) not in pids:
            continue
        major, minor, ino = fields[5].split(":")
        base = bases.get((os.makedev(int(major, 16), int(minor, 16)), int(ino)))
        if base is not None:
            found.add(base)
    return found


def belonging_to(names: set[str], owners: set[str]) -> set[str]:
    """The files among ``names`` of the segments in ``owners`` (segment names
    a process of ours was seen to map)."""
    return {n for n in names if _base(n) in owners}


def remove_orphans_of(names: set[str], owners: set[str], shm_dir: Path | str | None = None) -> list[Segment]:
    """Like :func:`remove_orphans`, limited to segments in ``owners``:
    never anyone else's orphans."""
    return remove_orphans(belonging_to(names, owners), shm_dir)
