"""Why a scenario cannot run on this machine, said in one line (None: it
can), for ``pytest.mark.skipif``. Black-box facts only: what the kernel
reports and what is installed, never the container's internals (the
container checks its own assumptions, and refuses, at start-up)."""

from __future__ import annotations

import os

from .report.env import cpuinfo

JEMALLOC = "/usr/lib/x86_64-linux-gnu/libjemalloc.so.2"  # Debian's libjemalloc2


def heap_keys_missing() -> str | None:
    """Why the container's ``--jemalloc --pkeys`` cannot be had here."""
    _, flags = cpuinfo()
    if "pku" not in flags:
        return "the CPU has no memory protection keys (no pku in /proc/cpuinfo)"
    if "ospke" not in flags:
        return "the kernel did not enable memory protection keys (no ospke in /proc/cpuinfo)"
    if not os.path.exists(JEMALLOC):
        return f"jemalloc is not installed ({JEMALLOC}: apt-get install libjemalloc2)"
    return None
