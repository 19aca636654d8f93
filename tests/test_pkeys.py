"""Memory protection keys: what the probe finds here, and what it says
where they are missing (container/isolated/pkeys.py, pkeys.c)."""

from __future__ import annotations

import errno
from dataclasses import replace
from pathlib import Path

import pytest

from cloneguard.container.isolated import pkeys


def _cpu_flags() -> set[str]:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("flags"):
            return set(line.split(":", 1)[1].split())
    return set()


HAS_PKU = {"pku", "ospke"} <= _cpu_flags()
needs_pku = pytest.mark.skipif(not HAS_PKU, reason="this CPU or kernel has no memory protection keys (pku, ospke)")


def test_the_probe_agrees_with_the_kernel():
    support = pkeys.probe()
    assert support.cpu_pku == ("pku" in _cpu_flags())
    assert support.os_pke == ("ospke" in _cpu_flags())
    if not HAS_PKU:
        assert support.keys == 0 and support.unavailable is not None
        assert support.describe().startswith("memory protection keys: no (")


@needs_pku
def test_every_fact_protection_rests_on_holds_here():
    support = pkeys.probe()
    # x86_64 has 16 keys; key 0 is everyone's. Fewer when something in
    # this process holds some (the probe frees all it takes).
    assert 1 <= support.keys <= 15
    assert support.alloc_errno == errno.ENOSPC
    assert support.mprotect_keeps and support.thread_inherits and support.write_faults
    assert support.unavailable is None
    assert support.describe() == f"memory protection keys: {support.keys} usable"
    # The probe gives back every key: a second one finds as many.
    assert pkeys.probe().keys == support.keys


SUPPORTED = pkeys.Support(
    cpu_pku=True,
    os_pke=True,
    keys=15,
    alloc_errno=errno.ENOSPC,
    pkru=pkeys.DEFAULT_PKRU,
    mprotect_keeps=True,
    thread_inherits=True,
    write_faults=True,
)


@pytest.mark.parametrize(
    "change, why",
    [
        ({"cpu_pku": False, "os_pke": False, "keys": 0}, "the CPU has no memory protection keys"),
        ({"os_pke": False, "keys": 0}, "the kernel did not enable memory protection keys"),
        ({"keys": 0, "alloc_errno": errno.EINVAL}, "pkey_alloc gives no key: Invalid argument"),
        ({"thread_inherits": False}, "not true here: a new thread starts with its creator's PKRU"),
        (
            {"mprotect_keeps": False, "write_faults": False},
            "not true here: a plain mprotect keeps a page's key; a write the PKRU forbids faults with SEGV_PKUERR",
        ),
    ],
)
def test_what_is_missing_is_said_in_one_line(change, why):
    support = replace(SUPPORTED, **change)
    assert support.unavailable is not None and support.unavailable.startswith(why)
    assert support.describe() == f"memory protection keys: no ({support.unavailable})"
    assert "\n" not in support.describe()
