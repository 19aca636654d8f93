"""GIL repair: children that die holding, handing over or waiting for the GIL.

Unlike tests/test_isolated_core.py these children die *inside* Python with
the GIL held (ctypes.string_at(0), os.abort(), os.kill(os.getpid(), ...)) or
inside the GIL's own machinery.  The monitor must undo that before it reports
the death, or this process freezes: everything that could freeze for good
when a mitigation is off runs in a subprocess with a timeout.
"""

from __future__ import annotations

import ctypes
import os
import select
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest
from gil_waiters import Counter, signal_while_gil_held, spawn_busy

from cloneguard.bench import random_kill as killbench
from cloneguard.container.isolated.core import CloneCore, Repair
from cloneguard.container.isolated.core_events import INTERPRETER_REPAIRS
from cloneguard.faults._gilfault import lib as gilfault
from cloneguard.harness import procfs

REPO = Path(__file__).resolve().parent.parent


@pytest.fixture
def counter():
    c = Counter()
    yield c
    c.stop()


@pytest.fixture
def core():
    c = CloneCore(crash_report=False)
    yield c
    c.close()


def assert_process_goes_on(core: CloneCore, counter: Counter) -> None:
    """The container's threads run Python, and so does a new child."""
    assert counter.advances(), "the container's counter thread stopped"
    out: dict[str, int] = {}
    child = core.spawn(lambda: out.update(x=sum(range(1000))))
    death = core.wait(child, 10)
    assert death is not None and death.exit_code == 0
    assert out == {"x": 499500}
    core.release(child)
    sys._current_frames()  # no thread state points at a freed stack


# --------------------------------------------------------------------------
# the child dies holding the GIL


def _string_at_zero():
    ctypes.string_at(0)  # PYFUNCTYPE: the GIL stays held


def _abort():
    os.abort()


def _kill_self():
    os.kill(os.getpid(), signal.SIGSEGV)


@pytest.mark.parametrize(
    "target, sig",
    [
        (_string_at_zero, signal.SIGSEGV),
        (_abort, signal.SIGABRT),
        (_kill_self, signal.SIGSEGV),
    ],
    ids=["string_at(0)", "os.abort", "os.kill-self"],
)
def test_a_child_dying_with_the_gil_is_repaired(core, counter, target, sig):
    seen = {}

    def child():
        seen["ident"] = threading.get_ident()
        for _ in range(1000):  # run a little: the GIL changes hands
            sum(range(100))
        target()

    c = core.spawn(child)
    death = core.wait(c, 10)
    assert death is not None, "death not reported: the monitor is stuck"
    assert death.exit_signal == sig
    assert death.gil_repaired and Repair.GIL_RELEASED in death.repairs
    assert counter.advances()
    # Its thread state is still linked (its stack is still mapped) until
    # release() unlinks it, with the GIL it got back.
    assert seen["ident"] in sys._current_frames()
    core.release(c)
    assert seen["ident"] not in sys._current_frames()
    assert_process_goes_on(core, counter)


# --------------------------------------------------------------------------
# the child dies inside the GIL's machinery (simulated at exact points)


@pytest.mark.parametrize(
    "where, expect",
    [
        (gilfault.GILFAULT_DROP_GIL_LOCKED, Repair.GIL_MUTEX | Repair.GIL_RELEASED),
        (gilfault.GILFAULT_TAKE_GIL_HANDOVER, Repair.GIL_MUTEX | Repair.SWITCH_MUTEX | Repair.GIL_RELEASED),
        (gilfault.GILFAULT_TAKE_GIL_CHECKING, Repair.GIL_MUTEX),
        (gilfault.GILFAULT_SWITCH_MUTEX, Repair.SWITCH_MUTEX),
        (gilfault.GILFAULT_DROP_GIL_SIGNALLING, Repair.GIL_MUTEX | Repair.COND_LOCK),
    ],
    ids=[
        "drop_gil-holding-mutex",
        "take_gil-hand-over",
        "take_gil-checking",
        "holding-switch_mutex",
        "drop_gil-inside-cond_signal",
    ],
)
def test_a_child_dying_inside_take_gil_or_drop_gil_is_repaired(core, counter, where, expect):
    c = core.spawn(lambda: gilfault.gilfault_die_in_gil(where))
    death = core.wait(c, 10)
    assert death is not None, "death not reported: the monitor is stuck"
    assert death.exit_signal == signal.SIGKILL
    # The GIL's own repairs exactly (what the interpreter needed besides,
    # after a death with the GIL held, depends on what it was doing).
    assert death.repairs & ~INTERPRETER_REPAIRS == expect, death.repairs
    core.release(c)
    assert_process_goes_on(core, counter)


def test_a_child_killed_while_waiting_for_the_gil_is_cancelled(core, counter):
    """This thread keeps the GIL in a C call (ctypes.PyDLL keeps it held) so
    the child blocks in take_gil's wait on gil->cond; another process kills
    it there.  Its condvar registration must be cancelled."""
    c = spawn_busy(core)
    signal_while_gil_held(c.pid, "KILL")
    death = core.wait(c, 10)
    assert death is not None and death.exit_signal == signal.SIGKILL
    assert Repair.COND_WAITER in death.repairs, death.repairs
    assert not death.gil_repaired
    core.release(c)
    assert_process_goes_on(core, counter)
    # The condvar still works for many hand-overs among three parties.
    sib = core.spawn(lambda: [sum(range(100)) for _ in range(20000)])
    assert core.wait(sib, 20).exit_code == 0
    core.release(sib)
    assert counter.advances()


# --------------------------------------------------------------------------
# random kills (the container side runs in subprocesses: see bench/random_kill.py)


def test_random_kills_in_a_tight_python_loop_all_survived():
    res = killbench.run(120, seed=20261122, hang_s=5.0, budget_s=150)
    print("\n" + res.line())
    assert res.kills == 120, res.line()
    assert (res.survived, res.hung, res.crashed) == (120, 0, 0), (res.line(), res.notes)
    # The kills landed in every part of the GIL's life.
    assert res.repairs["GIL_RELEASED"] > 10 and res.repairs["COND_WAITER"] > 10


def test_an_error_reading_the_random_kills_leaves_no_process_behind(monkeypatch):
    # Seen once: the reader raised (a name it looked up was gone) and the
    # worker, in a session of its own, spun on for an hour.
    started = []

    class Recorded(subprocess.Popen):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            started.append(self)

    def broken(self):
        raise RuntimeError("the reader's own error")

    monkeypatch.setattr(killbench.subprocess, "Popen", Recorded)
    monkeypatch.setattr(Repair, "names", broken)
    with pytest.raises(RuntimeError, match="the reader's own error"):
        killbench.run(5, seed=3, hang_s=5.0, budget_s=60)
    assert len(started) == 1 and started[0].returncode is not None
    # Nothing of its group is left (its killed victims, reparented, are
    # reaped by init a moment later).
    assert procfs.wait_group_empty(started[0].pid, 10), procfs.pids_in_group(started[0].pid)


def test_without_condvar_repair_random_kills_hang():
    """What condvar repair buys: without it a waiter's death soon hangs the
    next thread that signals the GIL's condvar (measured ~1 kill in 2)."""
    res = killbench.run(40, condvar_repair=False, seed=5, hang_s=3.0, budget_s=90, max_hangs=1)
    print("\n" + res.line())
    assert res.hung >= 1, res.line()


FREEZE_SCRIPT = textwrap.dedent("""
    import ctypes, sys, threading, time
    from cloneguard.container.isolated.core import CloneCore
    count = [0]
    def counter():
        while True:
            count[0] += 1
    threading.Thread(target=counter, daemon=True).start()
    core = CloneCore(gil_repair={gil_repair}, crash_report=False)
    go = threading.Event()
    child = core.spawn(lambda: go.wait() and ctypes.string_at(0))
    print("spawned", flush=True)
    go.set()
    death = core.wait(child, 30)
    start = count[0]
    time.sleep(0.2)
    print("survived", death.exit_signal, count[0] > start, flush=True)
    core.release(child)
    core.close()
""")


def _run_freeze_script(gil_repair: bool, timeout: float) -> tuple[list[str], bool]:
    """Lines printed within ``timeout``, and whether it was still running."""
    proc = subprocess.Popen(
        [sys.executable, "-c", FREEZE_SCRIPT.format(gil_repair=gil_repair)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        cwd=REPO,
        start_new_session=True,
    )
    assert proc.stdout is not None  # stdout=PIPE
    lines, buf = [], b""
    deadline = time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            r, _, _ = select.select([proc.stdout], [], [], max(0.0, deadline - time.monotonic()))
            if not r:
                break
            chunk = os.read(proc.stdout.fileno(), 4096)
            if not chunk:
                break
            buf += chunk
            lines = buf.decode().split()
            if b"survived" in buf and buf.endswith(b"\n"):
                break
        running = proc.poll() is None
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
    return lines, running


def test_without_gil_repair_a_child_dying_with_the_gil_freezes_the_process():
    lines, running = _run_freeze_script(gil_repair=False, timeout=10)
    assert "spawned" in lines, lines
    # Given 10 s to get its own death reported and a thread of its own to
    # count, it did neither: frozen (and killed by us).
    assert "survived" not in lines and running
    lines, running = _run_freeze_script(gil_repair=True, timeout=30)
    assert lines[-3:] == ["survived", "11", "True"], lines
