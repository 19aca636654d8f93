"""Which malloc the container runs on, and switching it to jemalloc.

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


class AllocatorUnavailable(RuntimeError):
    pass


def jemalloc_path() -> str | None:
    return next((p for p in JEMALLOC_PATHS if os.path.exists(p)), None)


def jemalloc_active() -> bool:
    return hasattr(ctypes.CDLL(None), "mallctl")


def describe() -> str:
    if not jemalloc_active():
        return "glibc malloc"
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
