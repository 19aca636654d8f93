"""Which malloc the container runs on, switching it to jemalloc, and glibc's arenas.

jemalloc must be in place before the first allocation, so ``--jemalloc``
re-executes the container with Debian's libjemalloc2 in LD_PRELOAD (the rest
of the command line and environment unchanged). Whether it is really in use
is checked, not assumed: jemalloc exports ``mallctl``, glibc does not.
"""
from __future__ import annotations

import ctypes
import os
import sys

JEMALLOC_PATHS = (
    "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2",   # Debian/Ubuntu libjemalloc2
    "/usr/lib64/libjemalloc.so.2",
    "/usr/lib/libjemalloc.so.2",
)
_REEXEC_MARK = "CLONEGUARD_JEMALLOC_REEXEC"


# glibc mallopt() parameter number of M_ARENA_MAX (malloc.h, glibc 2.36).
M_ARENA_MAX = -8
# Arenas glibc may create when each task gets its own. glibc's default is
# 8 per core, fixed the first time a thread finds the arenas exhausted: on
# 2 cores the 17th task (thread or node process) shares someone's arena.
OWN_ARENAS_MAX = 4096


class AllocatorUnavailable(RuntimeError):
    pass


def jemalloc_path() -> str | None:
    return next((p for p in JEMALLOC_PATHS if os.path.exists(p)), None)


def jemalloc_active() -> bool:
    return hasattr(ctypes.CDLL(None), "mallctl")


def glibc_arena_per_task() -> None:
    """Under glibc malloc: give every thread and node process an arena of
    its own instead of glibc's few shared ones. A task SIGKILLed inside
    malloc keeps its arena's lock for good; then whoever shares that arena
    hangs at its next malloc, however unrelated. With an arena each, only a
    task that frees the dead one's blocks can (a subscriber of its malloc'd
    messages; not of loaned ones: container.intra.pool). Costs address
    space (a heap reservation per arena), little memory. Must run before a
    second thread exists: glibc fixes its limit the first time it is reached."""
    global _own_arenas
    if jemalloc_active():
        return
    if ctypes.CDLL(None).mallopt(M_ARENA_MAX, OWN_ARENAS_MAX) != 1:
        raise AllocatorUnavailable("mallopt(M_ARENA_MAX) was refused")
    _own_arenas = True


_own_arenas = False


def describe() -> str:
    if not jemalloc_active():
        return "glibc malloc" + (", an arena per task" if _own_arenas else "")
    version = ctypes.c_char_p()
    size = ctypes.c_size_t(ctypes.sizeof(version))
    ctypes.CDLL(None).mallctl(b"version", ctypes.byref(version), ctypes.byref(size), None, 0)
    return f"jemalloc {version.value.decode()}"


def ensure_jemalloc(argv: list[str]) -> None:
    """Return if jemalloc is in use; else re-exec this process with it preloaded."""
    if jemalloc_active():
        return
    if os.environ.get(_REEXEC_MARK):
        raise AllocatorUnavailable(
            "jemalloc was preloaded but is not in use (LD_PRELOAD ignored?)")
    path = jemalloc_path()
    if path is None:
        raise AllocatorUnavailable(
            "libjemalloc.so.2 not found (Debian: apt-get install libjemalloc2)")
    env = dict(os.environ)
    env["LD_PRELOAD"] = " ".join(filter(None, [path, env.get("LD_PRELOAD", "")]))
    env[_REEXEC_MARK] = "1"
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *argv], env)
