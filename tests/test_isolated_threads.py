"""Threads created inside a child (the per-node profile's DDS threads).

glibc's pthread_create reads little of the *calling* thread's struct pthread:
the stack and pointer guards (tcbhead, set by the core), `flags`,
`schedpolicy`/`schedparam` (zero: inherit SCHED_OTHER), `eventbuf` and
`report_events` (zero: no debugger events) and `rseq_area.cpu_id` (-2 in a
child: the new thread does not register rseq).  Everything else the new
thread gets from allocate_stack, as any thread does.  The threads join the
child's thread group.
"""

from __future__ import annotations

import ctypes
import os
import threading
import time
from typing import Any

import pytest

from cloneguard.container.isolated.core import CloneCore

libc = ctypes.CDLL(None, use_errno=True)


@pytest.fixture
def core():
    c = CloneCore()
    yield c
    c.close()


def test_a_child_creates_and_joins_threads_100_times(core):
    out: dict[str, Any] = {"rounds": 0, "pids": set(), "tids": set(), "sums": set()}
    lock = threading.Lock()

    def work(i):
        with lock:
            out["pids"].add(os.getpid())
            out["tids"].add(threading.get_native_id())
            out["sums"].add(sum(range(i + 1000)) - sum(range(i)))

    def child():
        for r in range(100):
            ts = [threading.Thread(target=work, args=(r * 4 + k,)) for k in range(4)]
            for t in ts:
                t.start()
            for t in ts:
                t.join()
            out["rounds"] += 1
        out["child_pid"] = os.getpid()

    for _ in range(3):
        c = core.spawn(child)
        death = core.wait(c, 60)
        assert death is not None and death.exit_code == 0, death
        core.release(c)
        assert out["rounds"] == 100
        assert out["pids"] == {c.pid}  # in the child's thread group
        assert c.pid not in out["tids"] and len(out["tids"]) > 1
        out.update(rounds=0, pids=set(), tids=set())


def test_native_threads_created_in_a_child_run_and_join(core):
    """Plain pthread_create/pthread_join through ctypes, 100 times."""
    out = {}

    def child():
        START = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.c_void_p)
        start = START(lambda arg: (arg or 0) + 1)  # runs with the GIL
        libc.pthread_create.argtypes = [ctypes.POINTER(ctypes.c_ulong), ctypes.c_void_p, START, ctypes.c_void_p]
        libc.pthread_join.argtypes = [ctypes.c_ulong, ctypes.POINTER(ctypes.c_void_p)]
        results = []
        for i in range(100):
            t = ctypes.c_ulong()
            assert libc.pthread_create(ctypes.byref(t), None, start, i) == 0
            ret = ctypes.c_void_p()
            assert libc.pthread_join(t, ctypes.byref(ret)) == 0
            results.append(ret.value)
        out["results"] = results

    c = core.spawn(child)
    death = core.wait(c, 60)
    assert death.exit_code == 0
    assert out["results"] == list(range(1, 101))
    core.release(c)


def test_the_child_is_reported_dead_once_its_last_thread_is_gone(core):
    """The child's main task ends (raw exit) while a thread it created runs:
    the thread group, and so the child, lives until that thread ends."""

    def child():
        threading.Thread(target=time.sleep, args=(0.3,), daemon=True).start()

    t0 = time.monotonic()
    c = core.spawn(child)
    death = core.wait(c, 10)
    assert death.exit_code == 0
    assert time.monotonic() - t0 >= 0.25
    core.release(c)


def test_a_child_killed_with_threads_running_is_reaped(core):
    started = threading.Event()

    def child():
        for _ in range(4):
            threading.Thread(target=libc.pause, daemon=True).start()
        started.set()
        libc.pause()

    c = core.spawn(child)
    assert started.wait(10)
    core.kill(c)
    death = core.wait(c, 10)
    assert death is not None and death.exit_signal == 9
    core.release(c)
