"""Python's lock types for an isolated container (container/isolated/pylocks.c,
boot.py, container/locks.py): CPython's behaviour exactly, plus a holder.

The types are compared with CPython's own, call by call, in this process;
what needs them installed in place of CPython's (threading built on them, a
holder's process dying) runs in a process started through boot.py, or in a
real container.
"""

from __future__ import annotations

import _thread
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time

import pytest
from std_msgs.msg import UInt64

import cloneguard.container.isolated._pylocks as _pylocks  # an extension module
from cloneguard.faults import PACKAGE as TESTRIG

LOCKS = {"cpython": _thread.allocate_lock, "ours": _pylocks.allocate_lock}
RLOCKS = {"cpython": _thread.RLock, "ours": _pylocks.RLock}


def _outcome(call):
    try:
        return ("returned", call())
    except Exception as exc:
        return (type(exc).__name__, str(exc))


# Every way to call acquire on a held lock that returns or raises (the rest
# wait for ever, as they should).
ACQUIRE_ARGS = [
    (False,),
    (True, 0),
    (True, 0.01),
    (False, -1),
    (False, 1),
    (True, -2),
    (True, -0.5),
    (True, 1e20),
    (True, "x"),
    (True, None),
    (True, float("nan")),
    (True, float("inf")),
]


@pytest.mark.parametrize("args", ACQUIRE_ARGS, ids=repr)
@pytest.mark.parametrize("kind", ["lock", "rlock"])
def test_a_held_lock_answers_acquire_as_cpythons_does(kind, args):
    """On a lock another thread holds: the same result, or the same error."""
    seen = {}
    for impl, make in (LOCKS if kind == "lock" else RLOCKS).items():
        lock = make()
        holder = threading.Thread(target=lock.acquire)
        holder.start()
        holder.join()
        seen[impl] = _outcome(lambda lock=lock: lock.acquire(*args))
    assert seen["ours"] == seen["cpython"]


def test_lock_semantics_match_cpythons():
    results = {}
    for impl, make in LOCKS.items():
        lock, out = make(), []
        out.append(_outcome(lock.release))  # unlocked
        out.append((lock.acquire(), lock.locked(), lock.acquire(False)))
        t = threading.Thread(target=lock.release)  # any thread may release
        t.start()
        t.join()
        out.append(lock.locked())
        with lock:
            out.append(lock.locked())
        out.append((lock.acquire_lock(), lock.locked_lock(), lock.release_lock(), lock.locked()))
        lock.acquire()
        lock._at_fork_reinit()
        out.append(lock.locked())
        results[impl] = out
    assert results["ours"] == results["cpython"]


def test_rlock_semantics_match_cpythons():
    results = {}
    for impl, make in RLOCKS.items():
        lock, out = make(), []
        out.append(_outcome(lock.release))
        out.append((lock.acquire(), lock.acquire(), lock._recursion_count(), lock._is_owned()))
        other: dict[str, object] = {}
        t = threading.Thread(
            target=lambda lock=lock, other=other: other.update(
                release=_outcome(lock.release),
                owned=lock._is_owned(),
                count=lock._recursion_count(),
                try_=lock.acquire(False),
            )
        )
        t.start()
        t.join()
        out.append(sorted(other.items()))
        state = lock._release_save()
        out.append((state[0], state[1] == threading.get_ident(), lock._is_owned()))
        out.append(_outcome(lock._release_save))
        lock._acquire_restore(state)
        out.append((lock._recursion_count(), lock.release(), lock.release(), _outcome(lock.release)))
        results[impl] = out
    assert results["ours"] == results["cpython"]


def test_a_timed_acquire_gives_up_after_its_timeout():
    for make in LOCKS.values():
        lock = make()
        lock.acquire()
        started = time.monotonic()
        assert lock.acquire(timeout=0.2) is False
        assert 0.19 <= time.monotonic() - started < 2.0


def test_a_blocked_acquire_in_the_main_thread_runs_signal_handlers():
    """As CPython's: a SIGALRM handler that raises ends the wait with its
    exception; one that does not lets the wait go on."""
    for make in LOCKS.values():
        lock = make()
        lock.acquire()

        def interrupt(*_):
            raise KeyboardInterrupt

        old = signal.signal(signal.SIGALRM, interrupt)
        try:
            signal.setitimer(signal.ITIMER_REAL, 0.1)
            with pytest.raises(KeyboardInterrupt):
                lock.acquire(timeout=5)
            ticks: list[int] = []
            signal.signal(signal.SIGALRM, lambda *a, ticks=ticks: ticks.append(1))
            signal.setitimer(signal.ITIMER_REAL, 0.05)
            assert lock.acquire(timeout=0.3) is False and ticks == [1]
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)


def test_the_holder_is_known_while_held():
    lock = _pylocks.allocate_lock()
    assert lock.holder is None
    lock.acquire()
    assert lock.holder == (__import__("os").getpid(), threading.get_native_id())
    lock.release()
    assert lock.holder is None


def test_each_thread_is_its_own_holder_even_on_a_reused_stack():
    """The holder each thread records is kept per thread (pylocks.c: me());
    threads started one after another reuse the ended ones' stacks and TLS,
    and each must still record itself."""
    lock, seen = _pylocks.allocate_lock(), []

    def hold():
        with lock:
            seen.append((lock.holder, (os.getpid(), threading.get_native_id())))

    for _ in range(20):
        t = threading.Thread(target=hold)
        t.start()
        t.join()
    assert len(seen) == 20 and all(got == want for got, want in seen), seen


def test_a_node_process_records_itself_as_holder():
    """In a clone child (its own pid, a TLS block that an earlier child may
    have used): the holder is that child's pid and tid."""
    from cloneguard.container.isolated.core import CloneCore

    lock, seen = _pylocks.allocate_lock(), []

    def child():
        with lock:
            seen.append((lock.holder, (os.getpid(), threading.get_native_id())))

    core = CloneCore()
    try:
        for _ in range(5):
            c = core.spawn(child)
            core.wait(c, timeout=10)
            core.release(c)
    finally:
        core.close()
    assert len(seen) == 5 and all(got == want for got, want in seen), seen
    assert len({want for _, want in seen}) == 5


BOOTED = textwrap.dedent("""
    import json, queue, threading, logging
    from cloneguard.container import locks
    out = {"installed": locks.installed(),
           "types": sorted({type(threading.Lock()).__module__, type(threading.RLock()).__module__,
                            type(logging.Handler().lock).__module__})}
    q = queue.Queue(maxsize=1)
    threading.Thread(target=lambda: [q.put(i) for i in range(100)]).start()
    out["queue"] = sum(q.get() for _ in range(100))
    sem, ev = threading.BoundedSemaphore(2), threading.Event()
    threading.Timer(0.05, ev.set).start()
    out["event"] = ev.wait(5)
    out["semaphore"] = [sem.acquire(), sem.acquire(), sem.acquire(timeout=0.01)]
    print(json.dumps(out))
""")


def test_booted_threading_queue_and_logging_run_on_them(tmp_path):
    script = tmp_path / "booted.py"
    script.write_text(BOOTED)
    proc = subprocess.run(
        [sys.executable, "-m", "cloneguard.container.isolated.boot", str(script)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out == {
        "installed": True,
        "types": ["cloneguard.container.isolated._pylocks"],
        "queue": 4950,
        "event": True,
        "semaphore": [True, True, False],
    }


def test_boot_refuses_when_threading_came_first(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-c", "import threading\nfrom cloneguard.container.isolated import boot\nboot.install()"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode != 0 and "too late: threading is imported already" in proc.stderr


# -- in a container: a holder whose process died --------------------------------


@pytest.mark.parametrize("container_args", [["--isolated", "--no-python-locks"]])
def test_without_them_a_sibling_waits_for_a_dead_holder_forever(client, container):
    """The control: CPython's lock has no holder; nothing can take it over."""
    client.load_ok(TESTRIG, "faults::WaitsForPythonLock", parameters={"kind": "lock"})
    progress = client.subscribe(UInt64, "/python_lock_waiter/progress")
    progress.wait_count(5, timeout=10)
    holder = client.load_ok(TESTRIG, "faults::DieHoldingPythonLock", parameters={"kind": "lock", "delay": 0.05})
    from cloneguard_interfaces.msg import ComponentEvent

    client.wait_for_event(ComponentEvent.CRASHED, unique_id=holder.unique_id)
    time.sleep(0.5)  # the waiter's next use blocks (10 ms period)
    seen = len(progress)
    time.sleep(2)
    assert len(progress) == seen, "the waiter went on: the lock was given back"


@pytest.mark.parametrize("container_args", [["--isolated"]])
def test_with_them_the_sibling_takes_the_lock_over_at_once(client, container):
    from cloneguard_interfaces.msg import ComponentEvent

    client.load_ok(TESTRIG, "faults::WaitsForPythonLock", parameters={"kind": "rlock"})
    progress = client.subscribe(UInt64, "/python_lock_waiter/progress")
    progress.wait_count(5, timeout=10)
    holder = client.load_ok(TESTRIG, "faults::DieHoldingPythonLock", parameters={"kind": "rlock", "delay": 0.05})
    crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=holder.unique_id)
    repaired = client.wait_for_event(ComponentEvent.REPAIRED, unique_id=holder.unique_id, timeout=5)
    assert repaired.repaired_state == "python-lock"
    # It names the dead node, as its CRASHED did (after its death).
    assert (repaired.full_node_name, repaired.pid) == ("/python_lock_holder", crashed.pid)
    assert (
        "the Python RLock cloneguard.faults.shared_state.RLOCK, held by /python_lock_holder" in repaired.error_message
    )
    assert "taken over by /python_lock_waiter" in repaired.error_message
    delay_ns = (repaired.stamp.sec - crashed.stamp.sec) * 1_000_000_000 + repaired.stamp.nanosec - crashed.stamp.nanosec
    assert delay_ns < 2_000_000_000, delay_ns
    progress.wait_count(len(progress) + 10, timeout=5)
    assert "took cloneguard.faults.shared_state.RLOCK over from /python_lock_holder" in container.log_text()


@pytest.mark.parametrize("container_args", [["--isolated"]])
def test_a_lock_whose_holder_died_taking_it_is_reported_not_taken_over(client, container):
    """Its holder died between taking the lock word and recording itself:
    no holder is known, so nobody may take it over; the waiter says so on
    the log after STUCK_MS (1 s) of waiting."""
    from cloneguard_interfaces.msg import ComponentEvent

    client.load_ok(TESTRIG, "faults::WaitsForPythonLock", parameters={"kind": "lock"})
    progress = client.subscribe(UInt64, "/python_lock_waiter/progress")
    progress.wait_count(5, timeout=10)
    holder = client.load_ok(
        TESTRIG, "faults::DieHoldingPythonLock", parameters={"kind": "lock", "delay": 0.05, "taking": True}
    )
    client.wait_for_event(ComponentEvent.CRASHED, unique_id=holder.unique_id)
    container.wait_for_log(
        r"cloneguard: lock not repaired: /python_lock_waiter \(pid \d+\) thread \d+ has waited 1\.\d s for the "
        r"Python lock cloneguard\.faults\.shared_state\.LOCK, whose holder is not known",
        timeout=3.0,
    )
    seen = len(progress)
    time.sleep(0.5)
    assert len(progress) == seen, "the waiter went on: a lock with no holder known was taken over"
    assert not [e for e in client.events.messages() if e.event_type == ComponentEvent.REPAIRED]
