"""Which malloc the container runs on: jemalloc or glibc, the allocator
guard in front of it, and glibc's arenas.

Both must be in place before the first allocation, so the container
re-executes itself with them in LD_PRELOAD (the guard first, then Debian's
libjemalloc2; the rest of the command line and environment unchanged), and
takes them out of LD_PRELOAD again once running, so that programs it starts
do not inherit them. Whether each is really in use is checked, not assumed:
jemalloc exports ``mallctl``, the guard ``cga_activate``.
"""

from __future__ import annotations

import ctypes
import errno
import os
import sys
import sysconfig
from pathlib import Path

JEMALLOC_PATHS = (
    "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2",  # Debian/Ubuntu libjemalloc2
    "/usr/lib64/libjemalloc.so.2",
    "/usr/lib/libjemalloc.so.2",
)
# The allocator guard (container/isolated/allocguard/allocguard.c), built beside the package.
GUARD_PATH = str(Path(__file__).resolve().parent / "isolated" / f"_allocguard{sysconfig.get_config_var('EXT_SUFFIX')}")
_REEXEC_MARK = "CLONEGUARD_PRELOAD_REEXEC"
# Set to "0" in the environment the guard starts in: CPython keeps its own
# object allocator (pyalloc.c reads it before CPython starts).
PY_POOLS_OFF = "CLONEGUARD_PYALLOC"
# Set to "1" in the environment the guard starts in: it allocates memory
# protection keys for node heaps (isolated/allocguard/heapkeys.c) before main.
PKEYS_ON = "CLONEGUARD_PKEYS"


# glibc mallopt() parameter numbers (malloc.h, glibc 2.36).
M_ARENA_MAX = -8
M_MMAP_THRESHOLD = -3
# Arenas glibc may create when each task gets its own. glibc's default is
# 8 per core, fixed the first time a thread finds the arenas exhausted: on
# 2 cores the 17th task (thread or node process) shares someone's arena.
OWN_ARENAS_MAX = 4096
# glibc's initial mmap threshold, kept fixed. By default glibc raises it to
# the size of each mmapped block freed (up to 32 MiB); then a request of
# more than ~128 KiB that a non-main arena's full 64 MiB heap cannot hold
# makes sysmalloc create a new heap, free the old top into the arena, and
# heap_trim deletes the new (still empty) heap again: the request fails in
# that arena and glibc retries it in the *main* arena (measured, glibc 2.36:
# a thread allocating 16 B..2 MiB did so after ~5,000 allocations; with
# this threshold fixed, not once in 20 million). A node process would then
# allocate from, and hold the lock of, the container's own arena.
MMAP_THRESHOLD = 128 * 1024


#: The allocators --allocator names.
ALLOCATORS = ("jemalloc", "glibc")
JEMALLOC_MISSING = "libjemalloc.so.2 not found (Debian: apt-get install libjemalloc2)"


class AllocatorUnavailable(RuntimeError):
    pass


def jemalloc_path() -> str | None:
    return next((p for p in JEMALLOC_PATHS if os.path.exists(p)), None)


def jemalloc_active() -> bool:
    return hasattr(ctypes.CDLL(None), "mallctl")


def guard_loaded() -> bool:
    """Is the allocator guard preloaded into this process?"""
    return hasattr(ctypes.CDLL(None), "cga_activate")


def own_arenas() -> bool:
    """Has glibc_arena_per_task() raised glibc's arena limit here?"""
    return _own_arenas


def glibc_arena_per_task() -> None:
    """Under glibc malloc: give every thread and node process an arena of
    its own instead of glibc's few shared ones. A task SIGKILLed inside
    malloc keeps its arena's lock for good; then whoever shares that arena
    hangs at its next malloc, however unrelated. With an arena each, only a
    task that frees the dead one's blocks can (a subscriber of its malloc'd
    messages; not of loaned ones: container.intra.pool). Costs address
    space (a heap reservation per arena), little memory. Also keeps glibc's
    mmap threshold fixed (MMAP_THRESHOLD: why). Must run before a second
    thread exists: glibc fixes its limit the first time it is reached."""
    global _own_arenas
    if jemalloc_active():
        return
    libc = ctypes.CDLL(None)
    if libc.mallopt(M_ARENA_MAX, OWN_ARENAS_MAX) != 1:
        raise AllocatorUnavailable("mallopt(M_ARENA_MAX) was refused")
    if libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD) != 1:
        raise AllocatorUnavailable("mallopt(M_MMAP_THRESHOLD) was refused")
    _own_arenas = True


_own_arenas = False


def python_pools_active() -> bool:
    """Does the allocator guard serve CPython's object allocator here, with
    pools of their own for each node process (isolated/allocguard/pyalloc.c)? Not
    when PYTHONMALLOC chose another, or PY_POOLS_OFF turned it off."""
    lib = ctypes.CDLL(None)
    return hasattr(lib, "cga_py_active") and bool(lib.cga_py_active())


def heap_keys_asked() -> bool:
    """Did the guard start with protection keys asked for (PKEYS_ON)?"""
    lib = ctypes.CDLL(None)
    if not hasattr(lib, "cga_pkeys"):
        return False
    keys = (ctypes.c_int * 16)()
    return lib.cga_pkeys(keys, 16) != -errno.ENOENT


def describe() -> str:
    guard = ""
    if guard_loaded():
        guard = ", allocator guard" + (", Python object pools per process" if python_pools_active() else "")
    if not jemalloc_active():
        return "glibc malloc" + (", an arena per task" if _own_arenas else "") + guard
    version = ctypes.c_char_p()
    size = ctypes.c_size_t(ctypes.sizeof(version))
    ctypes.CDLL(None).mallctl(b"version", ctypes.byref(version), ctypes.byref(size), None, 0)
    return f"jemalloc {(version.value or b'?').decode()}" + guard


def ensure_preloaded(
    argv: list[str],
    *,
    guard: bool,
    jemalloc: bool,
    python_pools: bool = True,
    python_locks: bool = False,
    pkeys: bool = False,
) -> None:
    """Return once what is asked for is in use (the allocator guard, jemalloc;
    with ``python_locks``, Python's lock types that know their holder, which
    must be in place before anything imports threading: isolated/boot.py);
    else re-exec this process with it preloaded, through boot.py for the
    locks (``python_pools`` False: the guard leaves CPython's object
    allocator alone; ``pkeys``: the guard allocates protection keys for
    node heaps as it starts). Then take both out of LD_PRELOAD, for the
    programs this process starts."""
    from . import locks

    missing = []
    if guard and not guard_loaded():
        if not os.path.exists(GUARD_PATH):
            raise AllocatorUnavailable(f"the allocator guard is not built ({GUARD_PATH})")
        missing.append(GUARD_PATH)
    if jemalloc and not jemalloc_active():
        path = jemalloc_path()
        if path is None:
            raise AllocatorUnavailable(JEMALLOC_MISSING)
        missing.append(path)
    if python_locks and not locks.installed():
        missing.append("Python's lock types (isolated/boot.py)")
    if pkeys and guard_loaded() and not heap_keys_asked():
        missing.append("protection keys for node heaps (CLONEGUARD_PKEYS=1 as the guard starts)")
    if not missing:
        _scrub_preload()
        return
    if os.environ.get(_REEXEC_MARK):
        raise AllocatorUnavailable(f"{' and '.join(missing)} asked for but not in use (LD_PRELOAD ignored?)")
    env = dict(os.environ)
    # The guard comes first: its malloc and free are the ones every library
    # binds to, and it reaches jemalloc through mallocx & co.
    wanted = ([GUARD_PATH] if guard else []) + ([jemalloc_path() or ""] if jemalloc else [])
    rest = [p for p in env.get("LD_PRELOAD", "").split() if p not in wanted]
    env["LD_PRELOAD"] = " ".join(wanted + rest)
    env[_REEXEC_MARK] = "1"
    if not python_pools:
        env[PY_POOLS_OFF] = "0"
    if pkeys:
        env[PKEYS_ON] = "1"
    else:
        env.pop(PKEYS_ON, None)
    sys.stdout.flush()
    sys.stderr.flush()
    boot = ["-m", "cloneguard.container.isolated.boot"] if python_locks else []
    os.execve(sys.executable, [sys.executable, *boot, *argv], env)


def _scrub_preload() -> None:
    ours = {GUARD_PATH, *JEMALLOC_PATHS}
    left = [p for p in os.environ.get("LD_PRELOAD", "").split() if p not in ours]
    if left:
        os.environ["LD_PRELOAD"] = " ".join(left)
    else:
        os.environ.pop("LD_PRELOAD", None)
    os.environ.pop(_REEXEC_MARK, None)
    os.environ.pop(PY_POOLS_OFF, None)
    os.environ.pop(PKEYS_ON, None)
