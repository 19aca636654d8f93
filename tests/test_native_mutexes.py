"""The lock doctor (container/isolated/mutexes.c): a native mutex whose owner
died with its node process is released for the live task blocked on it;
one whose owner is alive is left alone; what it cannot prove or must not
touch is reported. Against the rig's C extension (faults/nativelock.c),
whose locks every node process of an isolated container shares."""

from __future__ import annotations

import re
import time

import pytest
from cloneguard_interfaces.msg import ComponentEvent
from std_msgs.msg import UInt64

from cloneguard.container.isolated import mappings
from cloneguard.container.isolated.core_events import MutexReport, MutexVerdict
from cloneguard.container.isolated.mutex_reports import kind_name, text
from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.faults._nativelock import lib as nativelock
from cloneguard.faults.components import NATIVE_LOCKS

ISOLATED = [["--isolated"]]
SIZEOF_MUTEX = 40  # pthread_mutex_t, x86_64


def _waiting(client, kind: str):
    client.load_ok(TESTRIG, "faults::WaitsForNativeMutex", parameters={"kind": kind})
    progress = client.subscribe(UInt64, "/native_mutex_waiter/progress")
    progress.wait_count(5, timeout=10)
    return progress


def _die(client, kind: str, how: str = "sigkill", **extra):
    holder = client.load_ok(
        TESTRIG, "faults::DieHoldingNativeMutex", parameters={"kind": kind, "how": how, "delay": 0.05, **extra}
    )
    return holder, client.wait_for_event(ComponentEvent.CRASHED, unique_id=holder.unique_id)


def _stalls(progress, for_s: float = 2.0) -> bool:
    """No progress over ``for_s`` (once the waiter's next use has blocked:
    it uses the lock every 10 ms)."""
    time.sleep(0.3)
    seen = len(progress)
    time.sleep(for_s)
    return len(progress) == seen


def _native_repairs(client, unique_id: int | None = None) -> list:
    return [
        e
        for e in client.events.messages()
        if e.event_type == ComponentEvent.REPAIRED
        and e.repaired_state == "native-mutex"
        and unique_id in (None, e.unique_id)
    ]


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec


@pytest.mark.parametrize("container_args", ISOLATED)
@pytest.mark.parametrize(
    ("kind", "how"),
    [("normal", "sigkill"), ("recursive", "segfault"), ("errorcheck", "sigkill"), ("adaptive", "segfault")],
)
def test_a_dead_owners_mutex_is_released_for_its_waiter(client, container, kind, how):
    progress = _waiting(client, kind)
    holder, crashed = _die(client, kind, how)
    repaired = client.wait_for_event(ComponentEvent.REPAIRED, unique_id=holder.unique_id, timeout=5)
    assert repaired.repaired_state == "native-mutex"
    message = repaired.error_message
    offset = NATIVE_LOCKS[kind] * SIZEOF_MUTEX
    assert re.search(rf"{kind.upper()} mutex 0x[0-9a-f]+ in _nativelock\S*\.so's data \(g_locks\+{offset}\)", message)
    assert f"held by /native_mutex_holder (pid {crashed.pid})" in message, message
    assert "released for /native_mutex_waiter" in message and "may be half-updated" in message
    assert _ns(repaired.stamp) - _ns(crashed.stamp) < 2_000_000_000
    progress.wait_count(len(progress) + 20, timeout=5)
    # The mutex works as before: the waiter keeps taking it, and a second
    # death holding it is repaired as the first.
    holder2, _ = _die(client, kind, how)
    client.wait_for_event(ComponentEvent.REPAIRED, unique_id=holder2.unique_id, timeout=5)
    progress.wait_count(len(progress) + 20, timeout=5)


@pytest.mark.parametrize("container_args", [["--isolated", "--no-mutex-repair"]])
def test_without_the_doctor_the_waiter_waits_for_ever(client, container):
    """The control: the same death, nothing released."""
    progress = _waiting(client, "normal")
    holder, _ = _die(client, "normal")
    assert _stalls(progress), "the waiter went on: the mutex was released"
    assert not _native_repairs(client, holder.unique_id)


@pytest.mark.parametrize("container_args", ISOLATED)
def test_a_live_owners_mutex_is_left_alone_after_another_death(client, container):
    """Another node dies while a live node holds the mutex: the waiter waits
    until the owner gives it back, and nothing is said of it."""
    client.load_ok(TESTRIG, "faults::HoldsNativeMutex", parameters={"kind": "normal", "hold": 4.0})
    started = time.monotonic()
    client.load_ok(TESTRIG, "faults::WaitsForNativeMutex", parameters={"kind": "normal"})
    progress = client.subscribe(UInt64, "/native_mutex_waiter/progress")
    _die(client, "errorcheck")  # a death: the doctor scans every waiter
    assert len(progress) == 0
    time.sleep(max(0.0, 3.0 - (time.monotonic() - started)))
    assert len(progress) == 0, "the waiter got a live owner's mutex"
    progress.wait_count(5, timeout=10)  # given back by its owner
    assert "native_mutex_waiter is blocked" not in container.log_text()
    assert not _native_repairs(client)


@pytest.mark.parametrize("container_args", ISOLATED)
def test_an_owner_not_proven_a_dead_nodes_is_reported_not_released(client, container):
    """A thread of a live node ends holding the mutex: its owner is gone, but
    was never a dead node process's task. After a death the stalled waiter
    is reported within 2 s, and the mutex is left as it is."""
    client.load_ok(TESTRIG, "faults::HoldsNativeMutex", parameters={"kind": "normal", "orphan": True})
    progress = _waiting_blocked(client, "normal")
    _, crashed = _die(client, "adaptive")
    container.wait_for_log(
        r"lock not repaired: .*native_mutex_waiter \(pid \d+\) thread \d+ is blocked on "
        r"native NORMAL mutex .* whose owner thread \d+ is gone but was not seen in a dead "
        r"node process: not released",
        timeout=2.0,
    )
    assert _stalls(progress, 1.0)


def _waiting_blocked(client, kind: str):
    client.load_ok(TESTRIG, "faults::WaitsForNativeMutex", parameters={"kind": kind})
    return client.subscribe(UInt64, "/native_mutex_waiter/progress")


@pytest.mark.parametrize("container_args", ISOLATED)
def test_a_mutex_held_with_no_owner_recorded_is_reported(client, container):
    """Its owner died between taking the lock word and writing itself down."""
    progress = _waiting(client, "normal")
    _die(client, "normal", "segfault", taking=True)
    container.wait_for_log(
        r"lock not repaired: .* blocked for over a second on native NORMAL mutex .* held "
        r"with no owner recorded .* the last node process to die was /native_mutex_holder",
        timeout=3.0,
    )
    assert _stalls(progress, 0.5)


@pytest.mark.parametrize("container_args", ISOLATED)
def test_a_robust_mutex_is_left_to_the_kernel(client, container):
    """The kernel marks a dead owner's robust mutex (each node process has
    its robust list): its next locker gets EOWNERDEAD; the doctor never
    touches it."""
    client.load_ok(TESTRIG, "faults::WaitsForNativeMutex", parameters={"kind": "robust"})
    progress = client.subscribe(UInt64, "/native_mutex_waiter/progress")
    repaired = client.subscribe(UInt64, "/native_mutex_waiter/repaired")
    progress.wait_count(5, timeout=10)
    _die(client, "robust")
    repaired.wait_count(1, timeout=5)
    progress.wait_count(len(progress) + 20, timeout=5)
    assert not _native_repairs(client)


@pytest.mark.parametrize("container_args", ISOLATED)
def test_a_glibc_internal_lock_a_dead_node_held_is_reported(client, container):
    """A stdio stream's lock records no owner: reported, not released."""
    progress = _waiting(client, "file")
    _die(client, "file", "segfault")
    container.wait_for_log(
        r"lock not repaired: .*native_mutex_waiter \(pid \d+\) thread \d+ has been blocked "
        r"for over a second on a glibc-internal lock .* since /native_mutex_holder \(pid "
        r"\d+\) died",
        timeout=3.0,
    )
    assert _stalls(progress, 0.5)


# -- the words, without a container ---------------------------------------------


def test_kinds_are_named():
    assert kind_name(0) == "NORMAL" and kind_name(512 | 1) == "RECURSIVE"
    assert (
        kind_name(16) == "robust NORMAL" and kind_name(128 | 32 | 2) == "priority-inheritance process-shared ERRORCHECK"
    )
    assert kind_name(-1) == "glibc-internal lock"


def test_an_address_is_named_by_the_library_symbol_it_lies_in():
    address = nativelock.nativelock_address(nativelock.NL_ADAPTIVE)
    want = rf"_nativelock\S*\.so's data \(g_locks\+{nativelock.NL_ADAPTIVE * SIZEOF_MUTEX}\)"
    assert re.fullmatch(want, mappings.describe(address))
    assert mappings.describe(0x10) == "unmapped memory"


def test_every_verdict_has_its_own_sentence():
    sentences = {
        text(MutexReport(0, 0, v, 0x1000, 1, 2, 0 if v != MutexVerdict.LIBC_LOCK else -1, 0)) for v in MutexVerdict
    }
    assert len(sentences) == len(MutexVerdict)
