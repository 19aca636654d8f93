"""The clone3(CLONE_VM) core: real children, real signals, real robust mutexes.

Every death here happens with the GIL released: a blocking syscall
(time.sleep, checked through /proc/<pid>/syscall) or a libc call through
ctypes.CDLL, which drops the GIL.  Deaths with the GIL held (os.abort(),
ctypes.string_at(0), os.kill(os.getpid(), ...)) need the monitor's GIL
repair: tests/test_isolated_gil.py.
"""

from __future__ import annotations

import ctypes
import errno
import faulthandler
import os
import resource
import select
import signal
import statistics
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from cloneguard.container.isolated.assumptions import IsolationUnavailable, self_check
from cloneguard.container.isolated.core import (
    Child,
    CloneCore,
    Death,
    StopRequested,
    in_child,
    stop_requested,
    wait_for_go,
)
from cloneguard.container.robust import MutexNotRecoverable, RobustMutex
from cloneguard.harness import procfs

libc = ctypes.CDLL(None, use_errno=True)
SYS_exit, SYS_kcmp, KCMP_VM = 60, 312, 1  # KCMP_VM is 1 (0 is KCMP_FILE)
NR_CLOCK_NANOSLEEP = 230  # what time.sleep blocks in (3.11, x86_64)


class Recorder:
    """on_event sink that tests can wait on."""

    def __init__(self) -> None:
        self.events: list = []
        self.cond = threading.Condition()
        self.threads: set[str] = set()
        self.arrived_ns: dict[int, int] = {}  # serial -> on_event time

    def __call__(self, event) -> None:
        now = time.monotonic_ns()
        with self.cond:
            self.arrived_ns.setdefault(event.serial, now)
            self.events.append(event)
            self.threads.add(threading.current_thread().name)
            self.cond.notify_all()

    def of(self, child) -> list:
        with self.cond:
            return [e for e in self.events if e.serial == child.serial]

    def wait_for(self, pred, timeout: float = 10.0) -> None:
        with self.cond:
            assert self.cond.wait_for(pred, timeout), f"timed out; events: {self.events}"


@pytest.fixture
def rec():
    return Recorder()


@pytest.fixture
def core(rec):
    c = CloneCore(on_event=rec)
    yield c
    c.close()


def wait_until(pred, timeout: float = 10.0, what: str = "condition") -> None:
    """Bounded poll for something only visible through /proc."""
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.001)


def blocked_in(pid: int, nr: int = NR_CLOCK_NANOSLEEP) -> bool:
    try:
        with open(f"/proc/{pid}/syscall") as f:
            return f.read().split()[0] == str(nr)
    except (OSError, IndexError):
        return False


def wait_sleeping(child) -> None:
    """Until the child is in time.sleep, i.e. has let go of the GIL."""
    wait_until(lambda: blocked_in(child.pid), what=f"child {child.pid} asleep")


def run(core, target, timeout: float = 10.0) -> Death:
    child = core.spawn(target)
    death = core.wait(child, timeout)
    assert death is not None, "child not reaped"
    core.release(child)
    return death


# --------------------------------------------------------------------------
# self_check


def test_self_check_passes_and_reports_layout():
    report = self_check()
    assert report.glibc == "2.36" and report.machine == "x86_64"
    assert report.layout.tid > 0 and report.layout.robust_head == report.layout.tid + 16
    assert "isolation available" in str(report)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(glibc_version="2.35"), "glibc version '2.35' is not supported"),
        (dict(machine="aarch64"), "machine 'aarch64' is not supported"),
        (dict(python_version=(3, 12)), "Python cpython 3.12 is not supported"),
        (dict(kernel_release="5.4.0-150-generic"), "kernel 5.4.0-150-generic is older"),
        (dict(overrides={"tid": 724}), "offset tid=724 does not hold"),
        (dict(overrides={"robust_head": 744}), "offset robust_head=744 does not hold"),
        (dict(overrides={"specific_1stblock": 800}), "specific_1stblock=800 does not hold"),
        (dict(overrides={"self": 0x08}), "offset self=0x8 does not hold"),
        (dict(overrides={"resp_tls": -144}), "offset resp_tls=-144 does not hold"),
        (dict(overrides={"robust_futex_offset": -24}), "robust_futex_offset=-24 does not hold"),
        (dict(overrides={"tid": 1 << 20}), "offset tid=1048576 lies outside struct pthread"),
    ],
)
def test_self_check_refuses_with_a_message_naming_the_failure(kwargs, message):
    with pytest.raises(IsolationUnavailable, match=message):
        self_check(**kwargs)


def test_self_check_rejects_unknown_override():
    with pytest.raises(ValueError, match="nope"):
        self_check(overrides={"nope": 1})


# --------------------------------------------------------------------------
# the child: own pid, shared memory, working libc


def test_child_has_own_pid_and_shares_the_address_space(core):
    seen = {}
    shared = bytearray(16)

    def child():
        seen["pid"] = os.getpid()
        seen["ppid"] = os.getppid()
        seen["ident"] = threading.get_ident()
        seen["in_child"] = in_child()
        seen["kcmp"] = libc.syscall(SYS_kcmp, os.getppid(), os.getpid(), KCMP_VM, 0, 0)
        shared[:5] = b"hello"

    c = core.spawn(child)
    death = core.wait(c, 10)
    assert death.exit_code == 0
    assert seen["pid"] == c.pid != os.getpid()
    assert seen["ppid"] == os.getpid()
    assert seen["ident"] != threading.get_ident()
    assert seen["in_child"] and not in_child()
    assert seen["kcmp"] == 0  # same mm as its parent
    assert bytes(shared[:5]) == b"hello"
    core.release(c)


def test_libc_and_python_work_in_the_child(core):
    out: dict[str, Any] = {}

    def child():
        x = 2.5
        out["fmt"] = (f"{1.5:f}", "%f" % x, f"{x:.3e}")  # noqa: UP031 (printf's own %f path, in a child)
        out["ctype"] = ("é".isalpha(), "7".isalpha(), libc.isalpha(ord("a")) != 0, libc.isalpha(ord("1")) != 0)
        buf = ctypes.create_string_buffer(64)
        libc.snprintf(buf, 64, b"%f|%d", ctypes.c_double(3.25), 42)
        out["snprintf"] = buf.value
        libc.malloc.restype = ctypes.c_void_p
        libc.free.argtypes = [ctypes.c_void_p]
        ptrs = []
        for i in range(20000):  # tcache and bins
            ptrs.append(libc.malloc(16 + (i * 37) % 4096))
            if len(ptrs) > 64:
                libc.free(ptrs.pop(0))
        for p in ptrs:
            libc.free(p)
        junk = [bytes(i % 300) for i in range(20000)]
        out["alloc"] = len(junk)
        t0 = time.monotonic()
        time.sleep(0.02)
        out["slept"] = time.monotonic() - t0
        out["time"] = time.time()
        out["strerror"] = os.strerror(errno.ENOENT)

    assert run(core, child).exit_code == 0
    assert out["fmt"] == ("1.500000", "2.500000", "2.500e+00")
    assert out["ctype"] == (True, False, True, False)
    assert out["snprintf"] == b"3.250000|42"
    assert out["alloc"] == 20000
    assert out["slept"] >= 0.02
    assert abs(out["time"] - time.time()) < 60
    assert out["strerror"] == "No such file or directory"


def _iconv(src: bytes, to: bytes, frm: bytes = b"UTF-8") -> bytes:
    """glibc iconv through ctypes (gconv modules keep PTR_MANGLEd pointers)."""
    libc.iconv_open.restype = ctypes.c_void_p
    libc.iconv_open.argtypes = [ctypes.c_char_p, ctypes.c_char_p]
    libc.iconv.argtypes = [ctypes.c_void_p] + [ctypes.c_void_p] * 4
    libc.iconv_close.argtypes = [ctypes.c_void_p]
    cd = libc.iconv_open(to, frm)
    assert cd not in (None, 2**64 - 1), "iconv_open failed"
    inbuf = ctypes.create_string_buffer(src, len(src))
    out = ctypes.create_string_buffer(4 * len(src) + 8)
    inp, outp = ctypes.c_char_p(ctypes.addressof(inbuf)), ctypes.c_char_p(ctypes.addressof(out))
    inleft, outleft = ctypes.c_size_t(len(src)), ctypes.c_size_t(len(out))
    n = libc.iconv(cd, ctypes.byref(inp), ctypes.byref(inleft), ctypes.byref(outp), ctypes.byref(outleft))
    libc.iconv_close(cd)
    assert n != 2**64 - 1 and inleft.value == 0
    return out.raw[: len(out) - outleft.value]


def test_child_uses_the_parents_mangled_pointers(core):
    """pointer_guard must equal the parent's: the parent loads a gconv module
    (its function pointers stored mangled), the child calls through them."""
    want = "h\u00e9llo".encode("iso8859-2")
    assert _iconv("h\u00e9llo".encode(), b"ISO-8859-2") == want
    out: dict[str, bytes] = {}
    assert run(core, lambda: out.update(r=_iconv("h\u00e9llo".encode(), b"ISO-8859-2"))).exit_code == 0
    assert out["r"] == want


def test_child_thread_descriptor_is_initialised(core):
    """The child's struct pthread holds what glibc's start_thread would give."""
    from cloneguard.container.isolated._clonecore import ffi, lib

    lay = self_check().layout

    def fields():
        tp = lib.cg_thread_pointer()

        def u64(off):
            return int(ffi.cast("uint64_t *", tp + off)[0])

        def i32(off):
            return int(ffi.cast("int32_t *", tp + off)[0])

        return dict(
            tp=tp,
            tcb=u64(lay.tcb),
            self=u64(lay.self),
            multiple_threads=i32(lay.multiple_threads),
            stack_guard=u64(lay.stack_guard),
            pointer_guard=u64(lay.pointer_guard),
            tid=i32(lay.tid),
            gettid=lib.cg_gettid(),
            robust=lib.cg_robust_list_head(),
            futex_offset=int(ffi.cast("int64_t *", tp + lay.robust_head + 8)[0]),
            specific0=u64(lay.specific),
            rseq_cpu_id=i32(lay.rseq_cpu_id),
            resp=u64(lay.resp_tls),
        )

    parent = fields()
    out = {}
    assert run(core, lambda: out.update(fields())).exit_code == 0
    tp = out["tp"]
    assert tp != parent["tp"]
    assert out["tcb"] == out["self"] == tp
    assert out["multiple_threads"] == 1
    assert out["stack_guard"] == parent["stack_guard"]
    assert out["pointer_guard"] == parent["pointer_guard"]
    assert out["tid"] == out["gettid"] != parent["tid"]
    assert out["robust"] == tp + lay.robust_head
    assert out["futex_offset"] == lay.robust_futex_offset
    assert out["specific0"] == tp + lay.specific_1stblock
    assert out["rseq_cpu_id"] == -2
    assert out["resp"] not in (0, parent["resp"])


def test_child_can_fork_and_run_subprocesses(core):
    """fork() in a child walks glibc's thread lists from the child's struct
    pthread (its list link must be valid); subprocess and the resolver work."""
    import socket

    out: dict[str, Any] = {}

    def child():
        out["sub"] = subprocess.run(["echo", "sub ok"], capture_output=True, text=True).stdout.strip()
        pid = os.fork()
        if pid == 0:
            os._exit(42)  # the forked copy, not the clone child
        out["fork"] = os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])
        out["addr"] = socket.getaddrinfo("localhost", 80, socket.AF_INET)[0][4]

    assert run(core, child).exit_code == 0
    assert out == {"sub": "sub ok", "fork": 42, "addr": ("127.0.0.1", 80)}


def test_stop_requested_outside_a_child_raises():
    with pytest.raises(RuntimeError, match="outside an isolated child"):
        stop_requested()


# --------------------------------------------------------------------------
# deaths


def _return():
    pass


def _raise():
    raise ValueError("deliberate")


def _sys_exit():
    sys.exit(7)


def _segv():
    libc.strlen(ctypes.c_void_p(0))  # a real fault, GIL released


def _segv_faulthandler():
    faulthandler._sigsegv(True)  # type: ignore[attr-defined]  # CPython's private test helper, not in typeshed; release_gil=True


def _abort():
    libc.abort()


@pytest.mark.parametrize(
    "target, code, sig",
    [
        (_return, 0, None),
        (_raise, 1, None),
        (_sys_exit, 7, None),
        (_segv, None, signal.SIGSEGV),
        (_segv_faulthandler, None, signal.SIGSEGV),
        (_abort, None, signal.SIGABRT),
    ],
)
def test_each_death_is_reported_once_and_parent_survives(core, rec, tmp_path, monkeypatch, target, code, sig):
    # Dumps on for the container: the child's own RLIMIT_CORE must still stop
    # a dump of the shared address space (and the kernel would write it here).
    old = resource.getrlimit(resource.RLIMIT_CORE)
    resource.setrlimit(resource.RLIMIT_CORE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
    monkeypatch.chdir(tmp_path)
    try:
        child = core.spawn(target)
        death = core.wait(child, 10)
        assert death is not None
        assert (death.exit_code, death.exit_signal) == (code, sig)
        assert death.si_code == (os.CLD_EXITED if sig is None else os.CLD_KILLED)
        assert not death.core_dumped
        assert resource.getrlimit(resource.RLIMIT_CORE)[0] == resource.RLIM_INFINITY
        # A second child afterwards: its death marks the end of the first's events.
        barrier = core.spawn(_return)
        core.wait(barrier, 10)
        rec.wait_for(lambda: any(e.serial == barrier.serial for e in rec.events))
        assert rec.of(child) == [death]
        assert rec.threads == {"cloneguard-core-listener"}
        assert not list(tmp_path.glob("core*")), "a core file was written"
        core.release(child)
        core.release(barrier)
    finally:
        resource.setrlimit(resource.RLIMIT_CORE, old)


def test_outside_sigkill_is_reported(core, rec):
    child = core.spawn(lambda: time.sleep(60))
    wait_sleeping(child)
    assert core.kill(child, signal.SIGKILL)
    death = core.wait(child, 10)
    assert (death.exit_signal, death.si_code) == (signal.SIGKILL, os.CLD_KILLED)
    assert core.kill(child) is False  # dead: pidfd says ESRCH
    rec.wait_for(lambda: death in rec.events)
    assert rec.of(child) == [death]
    core.release(child)
    # The killed child's thread state went with it: nothing points into its
    # unmapped stack.
    sys._current_frames()


def test_child_runs_with_core_dumps_off_and_parent_keeps_its_limit(core):
    child = core.spawn(lambda: time.sleep(60))
    wait_sleeping(child)
    limits = Path(f"/proc/{child.pid}/limits").read_text()
    line = next(ln for ln in limits.splitlines() if ln.startswith("Max core file size"))
    assert line.split()[4:6] == ["1", "1"], line
    assert resource.getrlimit(resource.RLIMIT_CORE) != (1, 1)
    core.kill(child)
    core.wait(child, 10)
    core.release(child)


# --------------------------------------------------------------------------
# robust mutexes


def _hold_then(mutex, ready: threading.Event, then):
    def child():
        mutex.lock()
        ready.set()
        then()

    return child


@pytest.mark.parametrize("how", ["sigkill", "raw_exit"])
def test_robust_mutex_owner_death_is_repaired(core, how):
    state = {"value": 1, "repairs": 0}
    ready = threading.Event()

    def repair():
        state["repairs"] += 1
        state["value"] = 0

    m = RobustMutex(repair=repair)
    if how == "sigkill":
        child = core.spawn(_hold_then(m, ready, lambda: time.sleep(60)))
        assert ready.wait(10)
        wait_sleeping(child)
        # Held by a live child: real exclusion (the tid in its TCB is right).
        with pytest.raises(TimeoutError):
            m.lock(timeout=0.05)
        core.kill(child)
    else:  # SYS_exit through ctypes: dies holding the mutex, GIL released
        child = core.spawn(_hold_then(m, ready, lambda: libc.syscall(SYS_exit, 3)))
    death = core.wait(child, 10)
    assert death is not None
    with m.held(timeout=10) as repaired:
        assert repaired
        assert state == {"value": 0, "repairs": 1}
    # Consistent again: plain lock/unlock, no further repair.
    assert m.lock(timeout=1) is False
    m.unlock()
    with m as repaired:  # the plain form
        assert not repaired
    assert state["repairs"] == 1
    core.release(child)


def test_robust_mutex_waiter_gets_owner_died_and_gil_is_free_while_blocked(core):
    m = RobustMutex()
    ready = threading.Event()
    child = core.spawn(_hold_then(m, ready, lambda: time.sleep(60)))
    assert ready.wait(10)
    wait_sleeping(child)
    result = {}
    blocked = threading.Event()

    def waiter():
        blocked.set()
        result["died"] = m.lock(timeout=10)
        m.mark_consistent()
        m.unlock()

    t = threading.Thread(target=waiter)
    t.start()
    tid = t.native_id
    assert tid is not None  # set before start() returns
    assert blocked.wait(10)
    wait_until(lambda: blocked_in(tid, 202), what="waiter in futex")
    # The waiter is blocked inside lock(); this thread still runs Python.
    count = sum(range(100000))
    assert count > 0
    core.kill(child)
    t.join(10)
    assert not t.is_alive() and result["died"] is True
    core.wait(child, 10)
    core.release(child)


def test_failed_repair_makes_the_mutex_unrecoverable(core):
    m = RobustMutex()
    ready = threading.Event()
    child = core.spawn(_hold_then(m, ready, lambda: libc.syscall(SYS_exit, 0)))
    core.wait(child, 10)

    def bad_repair():
        raise RuntimeError("cannot repair")

    with pytest.raises(RuntimeError, match="cannot repair"):
        with m.held(timeout=10, repair=bad_repair):
            pass
    with pytest.raises(MutexNotRecoverable):
        m.lock(timeout=1)
    core.release(child)


def test_robust_mutex_relock_by_owner_is_an_error():
    m = RobustMutex()
    m.lock()
    with pytest.raises(RuntimeError, match="already held"):
        m.lock()
    m.unlock()


# --------------------------------------------------------------------------
# graceful stop


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=lambda s: s.name)
def test_stop_signal_sets_the_stop_flag_and_the_child_ends_cleanly(core, rec, sig):
    """SIGINT as SIGTERM: Ctrl-C in a terminal signals the whole foreground
    process group, the children included."""
    looping = threading.Event()

    def child():
        while not stop_requested():
            looping.set()
            time.sleep(0.001)

    c = core.spawn(child)
    assert looping.wait(10)
    core.kill(c, sig)
    death = core.wait(c, 10)
    assert death.exit_code == 0
    rec.wait_for(lambda: death in rec.events)
    events = rec.of(c)
    assert [type(e) for e in events] == [StopRequested, Death]
    assert events[0].by_signal and events[0].pid == c.pid
    assert events[0].signal == sig
    core.release(c)


def test_a_stop_signal_landing_on_a_thread_the_child_created_reaches_the_child(core, rec):
    """A process-directed signal may be delivered to any thread of the child.
    Here only a thread the child created can take SIGINT; its handler (no
    cg_self there) passes it on to the child's main task, which sees it once
    it unblocks SIGINT."""
    state = {}
    armed = threading.Event()

    def child():
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        quit_helper = threading.Event()

        def helper():
            signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
            armed.set()  # only now can a process-directed SIGINT land here
            quit_helper.wait(30)

        t = threading.Thread(target=helper)
        t.start()

        # Pending on this task itself (SigPnd), forwarded by the helper's
        # handler: sigpending() also counts the process-wide set (ShdPnd),
        # where the signal sits until the helper takes it, and unblocking
        # then raced the helper's forward (seen once in a clean-clone run).
        def pending_here() -> bool:
            with open("/proc/thread-self/status") as f:
                line = next(x for x in f if x.startswith("SigPnd:"))
            return bool(int(line.split()[1], 16) & (1 << (signal.SIGINT - 1)))

        deadline = time.monotonic() + 10
        while not pending_here() and time.monotonic() < deadline:
            time.sleep(0.001)
        state["pending_on_main"] = pending_here()
        state["before_unblock"] = stop_requested()
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        state["after_unblock"] = stop_requested()
        quit_helper.set()
        t.join()

    c = core.spawn(child)
    assert armed.wait(10)
    core.kill(c, signal.SIGINT)
    death = core.wait(c, 20)
    assert death.exit_code == 0, death
    assert state == {"pending_on_main": True, "before_unblock": False, "after_unblock": True}
    rec.wait_for(lambda: death in rec.events)
    assert rec.of(c)[0].signal == signal.SIGINT
    core.release(c)


def test_parent_request_stop(core, rec):
    looping = threading.Event()

    def child():
        while not stop_requested():
            looping.set()
            time.sleep(0.001)
        sys.exit(5)

    c = core.spawn(child)
    assert looping.wait(10)
    assert core.request_stop(c) is True
    assert core.request_stop(c) is False  # already set
    death = core.wait(c, 10)
    assert death.exit_code == 5
    rec.wait_for(lambda: death in rec.events)
    assert [type(e) for e in rec.of(c)] == [StopRequested, Death]
    assert rec.of(c)[0].by_signal is False and rec.of(c)[0].signal is None
    core.release(c)


# --------------------------------------------------------------------------
# the gate: wait_for_go / go


def spawn_waiting_three_times(core):
    """A child that waits at its gate three times; what each wait returned."""
    passed = []

    def child():
        for _ in range(3):
            passed.append(wait_for_go())

    return core.spawn(child), passed


def test_each_go_lets_one_wait_through_and_none_is_lost(core):
    c, passed = spawn_waiting_three_times(core)
    core.go(c)
    core.go(c)  # both, maybe before the child waits at all
    wait_until(lambda: len(passed) == 2, what="two waits through")
    # The third waits; a broken gate would let it through and the child end.
    assert core.wait(c, timeout=0.3) is None
    assert len(passed) == 2
    core.go(c)
    assert core.wait(c, 10).exit_code == 0
    assert passed == [False, False, False]
    core.release(c)


@pytest.mark.parametrize("how", ["request_stop", "sigterm"])
def test_a_stop_ends_every_wait_at_the_gate(core, how):
    c, passed = spawn_waiting_three_times(core)
    core.go(c)
    wait_until(lambda: passed == [False], what="the first wait through")
    if how == "request_stop":
        core.request_stop(c)
    else:
        core.kill(c, signal.SIGTERM)
    assert core.wait(c, 10).exit_code == 0
    assert passed == [False, True, True]
    core.release(c)


def test_wait_for_go_outside_a_child_raises():
    with pytest.raises(RuntimeError, match="outside an isolated child"):
        wait_for_go()


# --------------------------------------------------------------------------
# the container dies -> the children die

CONTAINER_SCRIPT = textwrap.dedent("""
    import time
    from cloneguard.container.isolated.core import CloneCore
    core = CloneCore()
    child = core.spawn(lambda: time.sleep(3600))
    print(child.pid, flush=True)
    time.sleep(3600)
""")


def test_children_die_with_the_container():
    proc = subprocess.Popen([sys.executable, "-c", CONTAINER_SCRIPT], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None  # stdout=PIPE
    try:
        child_pid = int(proc.stdout.readline())
        pidfd = os.pidfd_open(child_pid)
    except BaseException:
        proc.kill()
        proc.wait()
        raise
    try:
        ready, _, _ = select.select([pidfd], [], [], 0)
        assert not ready, "child died before the container"
        proc.kill()
        proc.wait(10)
        ready, _, _ = select.select([pidfd], [], [], 10)
        assert ready, f"child {child_pid} outlived its SIGKILLed container"
    finally:
        os.close(pidfd)
        proc.stdout.close()


# --------------------------------------------------------------------------
# CLONE_INTO_CGROUP


def test_spawn_into_a_cgroup2_directory(core, request):
    root = Path("/sys/fs/cgroup/unified")
    if not (root / "cgroup.procs").exists():
        pytest.skip("no cgroup2 hierarchy at /sys/fs/cgroup/unified")
    cg = root / f"cloneguard-test-{os.getpid()}-{request.node.name[:20]}"
    cg.mkdir()
    try:
        fd = os.open(cg, os.O_RDONLY | os.O_DIRECTORY)
        try:
            child = core.spawn(lambda: time.sleep(60), cgroup_fd=fd)
            wait_sleeping(child)
            lines = Path(f"/proc/{child.pid}/cgroup").read_text().splitlines()
            assert f"0::/{cg.name}" in lines
            assert str(child.pid) in (cg / "cgroup.procs").read_text().split()
            core.kill(child)
            core.wait(child, 10)
            core.release(child)
        finally:
            os.close(fd)
    finally:
        wait_until(lambda: not (cg / "cgroup.procs").read_text().strip(), what="cgroup to empty")
        cg.rmdir()


# --------------------------------------------------------------------------
# release frees what spawn took


def _usage() -> dict[str, int]:
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmSize", "VmRSS"):
            out[key] = int(value.split()[0])  # KiB
    return out


def test_release_frees_stack_tls_and_pidfd_over_many_cycles(core):
    def cycles(n: int, killed: bool) -> None:
        for _ in range(n):
            c = core.spawn((lambda: time.sleep(60)) if killed else (lambda: [str(i) for i in range(100)]))
            if killed:
                wait_sleeping(c)
                core.kill(c)
            assert core.wait(c, 10) is not None
            core.release(c)

    # Warm-up: glibc gives early children new malloc arenas (reserved
    # address space) until its arena limit; after that they are reused.
    cycles(64, killed=False)
    fds_before, before = procfs.lasting_fds(os.getpid()), _usage()
    cycles(300, killed=False)
    cycles(100, killed=True)
    fds_after, after = procfs.lasting_fds(os.getpid()), _usage()
    print(f"\nusage before {before} after {after} (KiB)")
    # A leaked pidfd or event fd is one that is open after and was not
    # before. The count alone is not a measure: this is pytest's process,
    # and what earlier tests left (a garbage-collected socket, a joined
    # thread's file) may close meanwhile (one CI run: 23 -> 22).
    opened = {fd: t for fd, t in fds_after.items() if fds_before.get(fd) != t}
    assert opened == {}
    # One leaked 8 MiB stack would show; glibc keeps ~1 KiB per child (its
    # per-thread malloc cache, which only pthread's exit path frees).
    assert after["VmSize"] - before["VmSize"] < 8 * 1024
    assert after["VmRSS"] - before["VmRSS"] < 4 * 1024
    assert core.children() == []


def _thread_states() -> int:
    """The interpreter's thread states (C API: PyThreadState_Next)."""
    api = ctypes.pythonapi
    api.PyInterpreterState_Main.restype = ctypes.c_void_p
    api.PyInterpreterState_ThreadHead.restype = ctypes.c_void_p
    api.PyInterpreterState_ThreadHead.argtypes = [ctypes.c_void_p]
    api.PyThreadState_Next.restype = ctypes.c_void_p
    api.PyThreadState_Next.argtypes = [ctypes.c_void_p]
    n, t = 0, api.PyInterpreterState_ThreadHead(api.PyInterpreterState_Main())
    while t:
        n, t = n + 1, api.PyThreadState_Next(t)
    return n


def test_spawns_of_any_stack_size_free_everything_by_close(rec):
    # spawn() takes a block (stacks, thread state) made ahead for the last
    # stack size asked and makes the next: a change of size drops it, and
    # close() frees the one left over.
    before = _thread_states()
    core = CloneCore(on_event=rec)
    try:
        depth = []
        for size in (1 << 20, 1 << 20, 8 << 20, 256 << 10, 8 << 20):

            def deep(n=0):  # uses most of a 256 KiB stack
                return n if n >= 120 else deep(n + 1)

            c = core.spawn(lambda: depth.append(deep()), stack_size=size)
            death = core.wait(c, 10)
            assert death is not None and death.exit_code == 0
            core.release(c)
        assert depth == [120] * 5
        with pytest.raises(OSError, match="Invalid argument"):
            core.spawn(lambda: None, stack_size=4096)  # below 16 pages
    finally:
        core.close()
    # The listener thread has ended; every child's state and the one made
    # ahead are gone.
    assert _thread_states() == before


def test_close_lets_a_death_still_being_reported_finish_before_releasing():
    # A container stopping while a node's death is still in its handler
    # (the handler publishes CRASHED, destroys the node, then releases the
    # child): close() must not release that child under the handler's feet.
    box: list[Child]
    core: CloneCore  # assigned below, after on_event that uses it (else mypy takes the module's core fixture)
    gate, entered, outcome, box = threading.Event(), threading.Event(), [], []

    def on_event(event):
        if isinstance(event, Death):
            entered.set()
            gate.wait(30)
            try:
                core.release(box[0])
                outcome.append("released by its handler")
            except Exception as exc:
                outcome.append(repr(exc))

    core = CloneCore(on_event=on_event)
    try:
        box.append(core.spawn(lambda: None))
        assert entered.wait(10)
        closer = threading.Thread(target=core.close)
        closer.start()
        closer.join(1.0)
        assert closer.is_alive(), "close() did not wait for the death's handler"
        gate.set()
        closer.join(30)
        assert not closer.is_alive()
        assert outcome == ["released by its handler"]
    finally:
        gate.set()
        core.close()


# --------------------------------------------------------------------------
# contracts


def test_api_contracts(core):
    with pytest.raises(TypeError):
        core.spawn(42)
    with pytest.raises(RuntimeError, match="only one CloneCore"):
        CloneCore()
    c = core.spawn(lambda: time.sleep(60))
    with pytest.raises(RuntimeError, match="not been reaped"):
        core.release(c)
    with pytest.raises(RuntimeError, match="still alive"):
        core.close(kill=False)
    wait_sleeping(c)
    core.kill(c)
    core.wait(c, 10)
    core.release(c)
    with pytest.raises(ValueError):
        core.release(c)
    with pytest.raises(ValueError):
        core.kill(c)
    # A child cannot spawn children of its own (the core's one monitor
    # owns every child): it is told so, and the core is unchanged.
    raised = []
    c = core.spawn(lambda: raised.append(_raised_by(lambda: core.spawn(lambda: None))))
    assert core.wait(c, 10).exit_code == 0
    core.release(c)
    assert raised == [("RuntimeError", "spawn() from inside a child is not supported")]
    assert core.children() == []


def _raised_by(call) -> tuple[str, str] | None:
    try:
        call()
    except Exception as exc:
        return type(exc).__name__, str(exc)
    return None


def test_mitigations_are_chosen_per_core():
    from cloneguard.container.isolated.core import Mitigations

    with pytest.raises(TypeError, match="unknown mitigation"):
        CloneCore(gil_repairs=False)
    with pytest.raises(ValueError, match="jemalloc_arena"):
        CloneCore(jemalloc_arena="mine")
    base = Mitigations(crash_report=False)
    core = CloneCore(mitigations=base, condvar_repair=False)
    try:
        # alloc_guard None resolves to whether the guard is preloaded (not
        # here), mutex_repair and pybind11_ahead None to whether their checks pass
        assert core.mitigations == Mitigations(
            crash_report=False, condvar_repair=False, alloc_guard=False, mutex_repair=True, pybind11_ahead=True
        )
        assert Mitigations() == Mitigations(
            gil_repair=True,
            condvar_repair=True,
            interp_repair=True,
            crash_report=True,
            jemalloc_arena="own",
            jemalloc_tcache=True,
            container_gc=True,
            alloc_guard=None,
            mutex_repair=None,
            pybind11_ahead=None,
        )
    finally:
        core.close()


def test_close_kills_and_reaps_live_children(rec):
    core = CloneCore(on_event=rec)
    kids = [core.spawn(lambda: time.sleep(60)) for _ in range(3)]
    for k in kids:
        wait_sleeping(k)
    core.close()
    assert sorted(e.pid for e in rec.events) == sorted(k.pid for k in kids)
    assert all(e.exit_signal == signal.SIGKILL for e in rec.events)
    for k in kids:
        assert not Path(f"/proc/{k.pid}").exists()
    with pytest.raises(RuntimeError, match="closed"):
        core.spawn(_return)


# --------------------------------------------------------------------------
# latency (measured, not asserted)


def test_death_to_event_latency(core, rec):
    """Fault (or outside SIGKILL) -> monitor noticed -> on_event called."""
    detect, deliver, kill_detect = [], [], []
    shared = (ctypes.c_int64 * 1)()

    def crash():
        shared[0] = time.monotonic_ns()
        libc.strlen(ctypes.c_void_p(0))

    for _ in range(50):
        c = core.spawn(crash)
        death = core.wait(c, 10)
        assert death.exit_signal == signal.SIGSEGV
        rec.wait_for(lambda death=death: death in rec.events)
        detect.append(death.detected_monotonic_ns - shared[0])
        deliver.append(rec.arrived_ns[c.serial] - shared[0])
        core.release(c)
    for _ in range(50):
        c = core.spawn(lambda: time.sleep(60))
        wait_sleeping(c)
        t0 = time.monotonic_ns()
        core.kill(c)
        death = core.wait(c, 10)
        kill_detect.append(death.detected_monotonic_ns - t0)
        core.release(c)

    def us(xs):
        return f"median {statistics.median(xs) / 1e3:.0f} us, max {max(xs) / 1e3:.0f} us"

    print(
        f"\nSIGSEGV -> monitor: {us(detect)}; SIGSEGV -> on_event: {us(deliver)}; "
        f"outside SIGKILL -> monitor: {us(kill_detect)}"
    )


def test_the_monitor_blocks_every_signal_but_those_a_fault_raises():
    # A fault signal it blocked would kill the container silently (the
    # kernel delivers it with the default action, no handler run, no report).
    with CloneCore():
        tasks = Path(f"/proc/{os.getpid()}/task")
        [status] = [
            (t / "status").read_text() for t in tasks.iterdir() if (t / "comm").read_text().strip() == "cg-monitor"
        ]
        blocked = int(next(ln.split()[1] for ln in status.splitlines() if ln.startswith("SigBlk:")), 16)
    for sig in (signal.SIGSEGV, signal.SIGBUS, signal.SIGILL, signal.SIGFPE, signal.SIGABRT, signal.SIGTRAP):
        assert not blocked & (1 << (sig - 1)), f"{sig.name} is blocked on the monitor"
    for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGCHLD, signal.SIGUSR1):
        assert blocked & (1 << (sig - 1)), f"{sig.name} is not blocked on the monitor"


def test_the_monitor_runs_real_time_and_what_it_clones_does_not(core):
    """No node's use of the CPU may delay the monitor (a death's report,
    the memory watch's race against a leak): as root it is SCHED_FIFO at
    the lowest priority; its children get the ordinary policy
    (SCHED_RESET_ON_FORK)."""
    if os.geteuid() != 0:
        pytest.skip("SCHED_FIFO needs root or CAP_SYS_NICE (the refusal: the test below)")
    assert core.monitor_realtime() is None
    tasks = Path(f"/proc/{os.getpid()}/task")
    [monitor] = [int(t.name) for t in tasks.iterdir() if (t / "comm").read_text().strip() == "cg-monitor"]
    assert os.sched_getscheduler(monitor) == os.SCHED_FIFO | os.SCHED_RESET_ON_FORK
    assert os.sched_getparam(monitor).sched_priority == os.sched_get_priority_min(os.SCHED_FIFO)
    child = core.spawn(lambda: time.sleep(0.2))
    try:
        assert os.sched_getscheduler(child.pid) == os.SCHED_OTHER
    finally:
        core.wait(child)
        core.release(child)


def test_without_cap_sys_nice_the_monitor_says_why_it_is_not_real_time_and_children_run():
    """Where SCHED_FIFO is refused (an unprivileged user's container), the
    core says why and works as before: a child runs and its death is
    reported. Run without CAP_SYS_NICE by setpriv."""
    code = textwrap.dedent("""
        from cloneguard.container.isolated.core import CloneCore
        with CloneCore() as core:
            child = core.spawn(lambda: None)
            death = core.wait(child, 10)
            core.release(child)
            print(repr(core.monitor_realtime()), death.exit_code)
    """)
    drop = ["setpriv", "--inh-caps=-sys_nice", "--bounding-set=-sys_nice", "--"]
    out = subprocess.run([*drop, sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["'Operation", "not", "permitted'", "0"], out.stdout
