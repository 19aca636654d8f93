"""The lock doctor (container/isolated/clonecore/mutexes.c): a native mutex whose owner
died with its node process is released for the live task blocked on it;
one whose owner is alive is left alone; what it cannot prove or must not
touch is reported. Against the rig's C extension (faults/nativelock.c),
whose locks every node process of an isolated container shares."""

from __future__ import annotations

import errno
import re
import time

import pytest
from cloneguard_interfaces.msg import ComponentEvent
from std_msgs.msg import UInt64

from cloneguard.container.isolated import assumptions, mappings
from cloneguard.container.isolated.core_events import RWLOCK_KIND, MutexReport, MutexVerdict
from cloneguard.container.isolated.mutex_reports import kind_name, text
from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.faults._nativelock import lib as nativelock
from cloneguard.faults.components import NATIVE_LOCKS

ISOLATED = [["--isolated"]]
SIZEOF_MUTEX = 40  # pthread_mutex_t, x86_64


def _waiting(client, kind: str, wait: str = "lock", **extra):
    client.load_ok(TESTRIG, "faults::WaitsForNativeMutex", parameters={"kind": kind, "wait": wait, **extra})
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


def _repaired_lock(event) -> str:
    """What a REPAIRED event says it released: "NORMAL mutex", "rwlock", ..."""
    found = re.search(r"native (\w+ mutex|rwlock) 0x", event.error_message)
    return found[1] if found else event.error_message


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


# How a waiter waits (faults.components.NATIVE_WAITS), on which lock, and
# what the holder does: a timed lock retried every 0.2 s (what
# std::timed_mutex::try_lock_for in a loop does), the relock after a condvar
# wait that timed out (the holder takes the mutex while the waiter is inside
# that wait: its next step is the relock), a rwlock's writer or reader.
WAITS = [
    ("normal", "timedlock", {}),
    ("recursive", "timedlock", {}),
    ("errorcheck", "clocklock", {}),
    ("adaptive", "clocklock", {}),
    ("normal", "cond-timedwait", {"in_cond_wait": True}),
    ("normal", "cond-clockwait", {"in_cond_wait": True}),
    ("recursive", "cond-timedwait", {"in_cond_wait": True}),
    ("errorcheck", "cond-clockwait", {"in_cond_wait": True}),
    ("adaptive", "cond-timedwait", {"in_cond_wait": True}),
    ("rwlock", "lock", {}),
    ("rwlock", "read", {}),
]


@pytest.mark.parametrize("container_args", ISOLATED)
@pytest.mark.parametrize(("kind", "wait", "extra"), WAITS, ids=[f"{k}-{w}" for k, w, _ in WAITS])
def test_a_dead_owners_lock_is_released_whichever_way_its_waiter_waits(client, container, kind, wait, extra):
    """Each way of waiting is seen: a REPAIRED naming the lock within 2 s of
    the CRASHED, the waiter goes on, and a second death is repaired too."""
    progress = _waiting(client, kind, wait)
    holder, crashed = _die(client, kind, "sigkill", **extra)
    repaired = client.wait_for_event(ComponentEvent.REPAIRED, unique_id=holder.unique_id, timeout=5)
    assert repaired.repaired_state == "native-mutex"
    message = repaired.error_message
    if kind == "rwlock":
        assert re.search(r"rwlock 0x[0-9a-f]+ in _nativelock\S*\.so's data \(g_rwlock\+0\)", message), message
        assert f"write-locked by /native_mutex_holder (pid {crashed.pid})" in message, message
    else:
        offset = NATIVE_LOCKS[kind] * SIZEOF_MUTEX
        assert re.search(
            rf"{kind.upper()} mutex 0x[0-9a-f]+ in _nativelock\S*\.so's data \(g_locks\+{offset}\)", message
        )
        assert f"held by /native_mutex_holder (pid {crashed.pid})" in message, message
    assert "released for /native_mutex_waiter" in message and "may be half-updated" in message
    assert _ns(repaired.stamp) - _ns(crashed.stamp) < 2_000_000_000
    progress.wait_count(len(progress) + 20, timeout=5)
    holder2, _ = _die(client, kind, "segfault", **extra)
    client.wait_for_event(ComponentEvent.REPAIRED, unique_id=holder2.unique_id, timeout=5)
    progress.wait_count(len(progress) + 20, timeout=5)


@pytest.mark.parametrize("container_args", ISOLATED)
@pytest.mark.parametrize(("kind", "wait"), [("normal", "lock"), ("recursive", "clocklock")])
def test_a_dead_owners_mutex_is_released_while_its_waiter_holds_the_gil(client, container, kind, wait):
    """The waiter blocks holding the GIL (as rclpy's publish does inside Fast
    DDS), so no Python thread runs and the dead holder's process is not
    reaped (Python reaps it once told of the death): its main task, the
    owner, is a zombie that kill() still finds. It is dead all the same: the
    mutex is released and the container goes on (it hung for ever before:
    a CRASHED publish waited so on the send lock of a node killed in
    send_response)."""
    progress = _waiting(client, kind, wait, hold_gil=True)
    holder, crashed = _die(client, kind, waited=True)
    repaired = client.wait_for_event(ComponentEvent.REPAIRED, unique_id=holder.unique_id, timeout=5)
    assert f"held by /native_mutex_holder (pid {crashed.pid})" in repaired.error_message, repaired.error_message
    progress.wait_count(len(progress) + 20, timeout=5)


@pytest.mark.parametrize("container_args", ISOLATED)
@pytest.mark.parametrize("kind", ["normal", "recursive", "adaptive"])
def test_a_dead_owners_mutex_polled_with_trylock_is_found_and_released(client, container, kind):
    """A waiter that polls with trylock never blocks: the doctor finds the
    mutex by sweeping memory a second after the death (heldscan.c), still
    held by a dead task with nobody blocked on it, and releases it."""
    progress = _waiting(client, kind, "trylock")
    holder, crashed = _die(client, kind)
    repaired = client.wait_for_event(ComponentEvent.REPAIRED, unique_id=holder.unique_id, timeout=5)
    offset = NATIVE_LOCKS[kind] * SIZEOF_MUTEX
    assert re.search(
        rf"native {kind.upper()} mutex 0x[0-9a-f]+ in _nativelock\S*\.so's data \(g_locks\+{offset}\), still held "
        rf"by /native_mutex_holder \(pid {crashed.pid}\) thread \d+ a second after its process died, with no task "
        r"blocked on it",
        repaired.error_message,
    ), repaired.error_message
    assert 1_000_000_000 <= _ns(repaired.stamp) - _ns(crashed.stamp) < 2_000_000_000
    progress.wait_count(len(progress) + 20, timeout=5)
    assert len(_native_repairs(client, holder.unique_id)) == 1  # the one mutex, nothing else


@pytest.mark.parametrize("container_args", [["--isolated", "--no-mutex-repair"]])
@pytest.mark.parametrize("wait", ["lock", "timedlock", "trylock"])
def test_without_the_doctor_the_waiter_waits_for_ever(client, container, wait):
    """The control: the same death, nothing released (a timed waiter times
    out and tries again for ever)."""
    progress = _waiting(client, "normal", wait)
    holder, _ = _die(client, "normal")
    assert _stalls(progress), "the waiter went on: the mutex was released"
    assert not _native_repairs(client, holder.unique_id)


@pytest.mark.parametrize("container_args", ISOLATED)
@pytest.mark.parametrize(
    ("kind", "wait"), [("normal", "lock"), ("normal", "timedlock"), ("adaptive", "clocklock"), ("rwlock", "lock")]
)
def test_a_live_owners_mutex_is_left_alone_after_another_death(client, container, kind, wait):
    """Another node dies while a live node holds the mutex (or write-locks
    the rwlock): the waiter waits until the owner gives it back, and nothing
    is said of it."""
    client.load_ok(TESTRIG, "faults::HoldsNativeMutex", parameters={"kind": kind, "hold": 4.0})
    started = time.monotonic()
    client.load_ok(TESTRIG, "faults::WaitsForNativeMutex", parameters={"kind": kind, "wait": wait})
    progress = client.subscribe(UInt64, "/native_mutex_waiter/progress")
    _die(client, "errorcheck")  # a death: the doctor scans every waiter
    assert len(progress) == 0
    time.sleep(max(0.0, 3.0 - (time.monotonic() - started)))
    assert len(progress) == 0, "the waiter got a live owner's mutex"
    progress.wait_count(5, timeout=10)  # given back by its owner
    assert "native_mutex_waiter is blocked" not in container.log_text()
    # What was repaired is the dead node's own mutex (found held by the
    # sweep, nobody waiting on it), never the live owner's.
    assert [_repaired_lock(e) for e in _native_repairs(client)] == ["ERRORCHECK mutex"]


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
def test_a_rwlock_a_dead_node_read_locked_is_reported(client, container):
    """Readers record no owner: a writer blocked on it is reported after a
    second, and the rwlock is left as it is."""
    progress = _waiting(client, "rwlock")
    _die(client, "rwlock", reading=True)
    container.wait_for_log(
        r"lock not repaired: .*native_mutex_waiter \(pid \d+\) thread \d+ has been blocked for over a second on "
        r"native rwlock 0x[0-9a-f]+ .*held by readers or with no writer recorded \(glibc records no reader",
        timeout=3.0,
    )
    assert _stalls(progress, 0.5)
    assert not _native_repairs(client)


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
    rwlock = {v: text(MutexReport(0, 0, v, 0x1000, 1, 2, RWLOCK_KIND, 0)) for v in MutexVerdict if v != v.LIBC_LOCK}
    assert all("rwlock 0x1000" in t for t in rwlock.values())
    assert not set(rwlock.values()) & sentences
    assert "glibc records no reader" in rwlock[MutexVerdict.NO_OWNER]


# -- the start-up probe of timed and rwlock waits ----------------------------------


def test_timed_and_rwlock_waits_are_probed_here():
    report = assumptions.self_check()
    assert report.timed_wait_unavailable == ""
    L = report.layout
    assert L.timed_wait_pc not in (0, L.mutex_wait_pc, L.private_wait_pc)
    assert all(L.mutex_timed_ret) and all(L.rwlock_ret)
    assert not set(L.mutex_timed_ret) & (set(L.mutex_ret) | set(L.rwlock_ret))
    # __writers_futex (writers on a writer), then __wrphase_futex (readers on
    # a writer, writers on readers)
    assert L.rwlock_futex_off == (12, 12, 12, 8, 8, 8, 8, 8, 8)


class _ProbeFails:
    """The core's lib, but cg_probe_timedwait fails."""

    def __init__(self, lib):
        self._lib = lib

    def __getattr__(self, name):
        return getattr(self._lib, name)

    def cg_probe_timedwait(self, p):
        return -errno.ENOENT


def test_a_failed_timed_probe_recognizes_none_of_those_waits_and_says_why():
    ffi, lib = assumptions.core_module()
    good = assumptions.self_check().layout
    for fake_lib, layout, why in [
        (_ProbeFails(lib), good, "timed waiter probe failed"),
        (lib, assumptions.Layout(**{**good.as_dict(), "mutex_wait_pc": 0}), "plain mutex waits are not recognized"),
    ]:
        ck = assumptions._Checker()
        L, unavailable = assumptions._probe_timedwait(ck, ffi, fake_lib, layout, {})
        assert why in unavailable
        assert (L.timed_wait_pc, L.timed_ret_slot) == (0, 0)
        assert not any(L.mutex_timed_ret) and not any(L.rwlock_ret) and not any(L.rwlock_futex_off)
        assert not ck.failed  # isolation itself is not refused
