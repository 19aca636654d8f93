"""Crash reports: a child that faults says where, then dies of that signal.

The report goes to fd 2, which the children share with the container (and
capfd captures).  Deaths with the GIL held rely on GIL repair (on by default).
"""

from __future__ import annotations

import ctypes
import mmap
import os
import re
import signal
import tempfile
import threading

import pytest

from cloneguard.container.isolated.core import CloneCore

libc = ctypes.CDLL(None, use_errno=True)


def _segv_gil_released():
    libc.strlen(ctypes.c_void_p(0))


def _segv_gil_held():
    ctypes.string_at(0)


def _abort():
    os.abort()


def _bus():
    """A real SIGBUS: touch a page of a file mapping beyond the file's end."""
    with tempfile.TemporaryFile() as f:
        f.truncate(8192)
        m = mmap.mmap(f.fileno(), 8192)
        f.truncate(0)
        m[4096]


def _sent(sig):
    def target():
        os.kill(os.getpid(), sig)

    return target


@pytest.fixture
def core():
    c = CloneCore()
    yield c
    c.close()


@pytest.mark.parametrize(
    "target, sig, fault",
    [
        (_segv_gil_released, signal.SIGSEGV, True),
        (_segv_gil_held, signal.SIGSEGV, True),
        (_bus, signal.SIGBUS, True),
        (_abort, signal.SIGABRT, False),
        (_sent(signal.SIGFPE), signal.SIGFPE, False),
        (_sent(signal.SIGILL), signal.SIGILL, False),
    ],
    ids=["segv", "segv-gil-held", "bus", "abort", "fpe-sent", "ill-sent"],
)
def test_a_crashing_child_reports_and_still_dies_of_the_signal(core, capfd, target, sig, fault):
    c = core.spawn(target)
    death = core.wait(c, 10)
    assert death is not None
    assert (death.exit_signal, death.si_code) == (sig, os.CLD_KILLED)
    # The child wrote the head before it died; the container writes its
    # Python and native stacks after reporting the death.
    assert core.flush_crash_reports(10)
    err = capfd.readouterr().err
    name = signal.Signals(sig).name
    where = r"0x[0-9a-f]+" if fault else "-"
    head = rf"cloneguard: pid {c.pid} caught {name} at {where} \(pc 0x[0-9a-f]+\)\n"
    found = re.search(head, err)
    assert found, err
    if sig == signal.SIGSEGV:
        assert f"caught {name} at 0x0 " in err
    python = err.index(f"cloneguard: pid {c.pid} Python stack (most recent call first):\n")
    native = err.index(f"cloneguard: pid {c.pid} native stack:\n")
    assert found.start() < python < native
    # The Python frames, innermost first, as faulthandler writes them.
    frames = err[python:native].splitlines()[1:]
    assert frames and all(re.fullmatch(r'  File ".+", line \d+ in \S+', f) for f in frames), frames
    first = target.__code__.co_firstlineno
    lines = [
        int(m.group(1))
        for f in frames
        if (m := re.fullmatch(rf'  File "{re.escape(__file__)}", line (\d+) in {target.__name__}', f))
    ]
    assert len(lines) == 1 and first < lines[0] <= first + 8, frames
    assert "libc.so.6" in err[native:] and "_clonecore" in err[native:]  # frames, symbolized
    assert err.count("cloneguard: pid") == 3 and "cloneguard: native stack:" not in err
    core.release(c)


def test_a_deep_python_stack_is_written_to_its_innermost_100_frames(core, capfd):
    def deep(n):
        return deep(n - 1) if n else _segv_gil_released()

    c = core.spawn(lambda: deep(150))
    assert core.wait(c, 10).exit_signal == signal.SIGSEGV
    assert core.flush_crash_reports(10)
    err = capfd.readouterr().err
    python = err.index(f"cloneguard: pid {c.pid} Python stack (most recent call first):\n")
    frames = err[python : err.index(f"cloneguard: pid {c.pid} native stack:\n")].splitlines()[1:]
    assert len(frames) == 101 and frames[-1] == "  ..."
    assert frames[0].endswith(" in _segv_gil_released") and all(f.endswith(" in deep") for f in frames[1:-1])
    core.release(c)


def test_a_crash_in_a_thread_the_child_created_is_reported_too(core, capfd):
    def child():
        t = threading.Thread(target=_segv_gil_released)
        t.start()
        t.join()

    c = core.spawn(child)
    death = core.wait(c, 10)
    assert death.exit_signal == signal.SIGSEGV
    err = capfd.readouterr().err
    m = re.search(
        rf"cloneguard: pid {c.pid} caught SIGSEGV at 0x0 \(pc 0x[0-9a-f]+\)\n"
        r"cloneguard: si_code \d+, thread (\d+)\n",
        err,
    )
    assert m and int(m.group(1)) != c.pid, err
    # That thread has no control block of its own: it symbolized in place.
    assert core.flush_crash_reports(10)
    assert "cloneguard: native stack:\n" in err and "native stack:" not in capfd.readouterr().err
    core.release(c)


def test_crash_reports_can_be_turned_off(capfd):
    with CloneCore(crash_report=False) as core:
        c = core.spawn(_segv_gil_released)
        death = core.wait(c, 10)
        assert death is not None and death.exit_signal == signal.SIGSEGV
        core.release(c)
    assert "cloneguard:" not in capfd.readouterr().err


def test_a_clean_exit_and_an_outside_kill_write_no_report(core, capfd):
    c = core.spawn(lambda: None)
    assert core.wait(c, 10).exit_code == 0
    core.release(c)
    ready = threading.Event()

    def sleeper():
        ready.set()
        libc.pause()

    c = core.spawn(sleeper)
    assert ready.wait(10)
    core.kill(c, signal.SIGKILL)
    assert core.wait(c, 10).exit_signal == signal.SIGKILL
    core.release(c)
    assert "cloneguard:" not in capfd.readouterr().err


def test_closing_the_core_ends_its_crash_stack_writer(capfd):
    with CloneCore() as core:
        c = core.spawn(_segv_gil_released)
        death = core.wait(c, 10)
        assert death is not None and death.exit_signal == signal.SIGSEGV
        core.release(c)
        assert core.flush_crash_reports(10)
        assert any(t.name == "cloneguard-crash-stacks" for t in threading.enumerate())
    assert not any(t.name == "cloneguard-crash-stacks" for t in threading.enumerate())
    assert f"cloneguard: pid {c.pid} native stack:" in capfd.readouterr().err
