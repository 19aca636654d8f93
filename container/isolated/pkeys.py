"""Memory protection keys on this machine: whether they exist, how many,
and whether the facts per-node heap protection rests on hold here
(pkeys.c names them and how each is checked); and the keys the allocator
guard put over node heaps (heapkeys.c, the container's --pkeys).

``probe()`` runs the check on the calling thread; ``Support.unavailable``
says in one line why keys cannot protect anything here, or None.
``heap_keys_unavailable()`` says why --pkeys cannot be had, or None."""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass

# What a thread's PKRU holds by default on Linux x86_64: every key but 0
# access-disabled (the kernel's init_pkru), so that pages under a key are
# untouchable by threads that never asked for it.
DEFAULT_PKRU = 0x55555554
# Why there are no keys at all, whether learnt from CPUID (the probe) or
# from /proc/cpuinfo (cpu_lacks_keys).
NO_PKU = "the CPU has no memory protection keys (no pku in /proc/cpuinfo)"
NO_OSPKE = "the kernel did not enable memory protection keys (no ospke in /proc/cpuinfo)"


@dataclass(frozen=True)
class Support:
    cpu_pku: bool  # the CPU has protection keys
    os_pke: bool  # and the kernel enabled them
    keys: int  # pkey_alloc hands out this many
    alloc_errno: int  # why it stopped (ENOSPC once all are out)
    pkru: int  # the probing thread's PKRU
    mprotect_keeps: bool | None  # None: not probed (no keys)
    thread_inherits: bool | None
    write_faults: bool | None

    @property
    def unavailable(self) -> str | None:
        """Why keys cannot protect a node's heap here, or None."""
        if not self.cpu_pku:
            return NO_PKU
        if not self.os_pke:
            return NO_OSPKE
        if self.keys == 0:
            return f"pkey_alloc gives no key: {os.strerror(self.alloc_errno)}"
        broken = [
            what
            for what, ok in (
                ("a plain mprotect keeps a page's key", self.mprotect_keeps),
                ("a new thread starts with its creator's PKRU", self.thread_inherits),
                ("a write the PKRU forbids faults with SEGV_PKUERR", self.write_faults),
            )
            if not ok
        ]
        return "not true here: " + "; ".join(broken) if broken else None

    def describe(self) -> str:
        """One line for the container's log."""
        why = self.unavailable
        return f"memory protection keys: {self.keys} usable" if why is None else f"memory protection keys: no ({why})"


def probe() -> Support:
    from cloneguard.container.isolated._clonecore import ffi, lib

    p = ffi.new("struct cg_pkeys_probe *")
    lib.cg_pkeys_probe(p)

    def fact(v: int) -> bool | None:
        return None if v < 0 else bool(v)

    return Support(
        cpu_pku=bool(p.cpu_pku),
        os_pke=bool(p.os_pke),
        keys=int(p.keys),
        alloc_errno=int(p.alloc_errno),
        pkru=int(p.pkru),
        mprotect_keeps=fact(p.mprotect_keeps),
        thread_inherits=fact(p.thread_inherits),
        write_faults=fact(p.write_faults),
    )


# Why node heaps on glibc malloc stay unkeyed (protection keys are on by
# default only where jemalloc is): the guard routes a node process's
# allocations by caller, the ROS stack's and the interpreter's to memory
# every node writes (heapkeys.c); glibc picks an arena per thread, not per
# call, so they would land under the node's key and fault the next node
# that writes them (Fast DDS's payload pools, rclpy's registry: the isolated
# README).
NEEDS_JEMALLOC = (
    "node heaps are keyed on jemalloc only (the default; not --allocator glibc): glibc picks an "
    "arena per thread, not per call, so what the ROS stack allocates in a node process could not "
    "stay writable by every node"
)


def cpu_lacks_keys() -> str | None:
    """Why this CPU or kernel has no protection keys, from /proc/cpuinfo
    (no probe, no key taken), or None."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError as exc:
        return f"/proc/cpuinfo unreadable: {exc}"
    if "pku" not in flags:
        return NO_PKU
    if "ospke" not in flags:
        return NO_OSPKE
    return None


def heap_keys() -> list[int] | str:
    """The keys the allocator guard holds for node heaps, or why none."""
    from cloneguard.container.isolated._clonecore import ffi, lib

    keys = ffi.new("int[16]")
    n = lib.cg_pkeys_in_use(keys, 16)
    if n == -errno.ENOENT:
        return "the allocator guard did not start with them (CLONEGUARD_PKEYS=1)"
    if n == -errno.ENOSYS:
        return "the CPU or kernel has no memory protection keys (no pku/ospke in /proc/cpuinfo)"
    if n < 0:
        return f"pkey_alloc gave no key: {os.strerror(-n)}"
    return [keys[i] for i in range(n)]


def heap_keys_unavailable() -> str | None:
    """Why node heaps cannot be under protection keys here, or None."""
    keys = heap_keys()
    if isinstance(keys, str):
        return keys
    return probe().unavailable


def heap_keys_describe() -> str:
    keys = heap_keys()
    if isinstance(keys, str):
        return f"memory protection keys over node heaps: off ({keys})"
    return (
        f"memory protection keys over node heaps: {len(keys)} keys ({', '.join(map(str, keys))}), one per "
        f"live node process; past {len(keys)} live at once, a node shares a key with a live one, and is not "
        "protected from it"
    )
