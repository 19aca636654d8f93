"""Every assumption the isolated core rests on, in one place, each one checked.

The C core (core.h lists its files) builds a glibc thread descriptor by hand
for a task glibc did not create.  That is only sound on a platform we have
looked at, with the struct pthread layout we believe in.  This module says which platforms
those are, finds every layout value at run time (from glibc's own debugger
descriptors, the kernel's view of the calling thread, and exported symbols)
and checks each one against the live calling thread before any child exists.

``self_check()`` returns a Report or raises IsolationUnavailable naming every
check that failed.  Its keyword arguments fake what it would otherwise read
(glibc version, Python version, machine, kernel release, any layout value), so
a test can show the refusal and its message.

Where each value comes from and how it is checked:

  tcbhead_t (sysdeps/x86_64/nptl/tls.h; x86_64 ABI: gcc emits %fs:0x28 for the
  stack protector, glibc's PTR_MANGLE uses %fs:0x30):
    tcb 0x00, self 0x10   both must hold the thread pointer itself
    multiple_threads 0x18 0/1; must be 1 once the process has a second thread
    stack_guard 0x28      non-zero
    pointer_guard 0x30    non-zero
    feature_1 0x48        must be 0: CET (IBT/SHSTK) is not handled
  struct pthread (nptl/descr.h):
    tid              _thread_db_pthread_tid; TCB+tid == gettid()
    list             _thread_db_pthread_list; list.next->prev == &list
    robust_head      kernel's get_robust_list(0) - TCB; must be tid + 16
                     (tid, robust_prev, robust_head: __PTHREAD_MUTEX_HAVE_PREV)
    robust_futex_offset  head.futex_offset as glibc set it; must equal
                     offsetof(__lock) - offsetof(__list.__next) (compiled)
    specific         _thread_db_pthread_specific (32 pointers)
    specific_1stblock  specific - 32 * _thread_db_sizeof_pthread_key_data;
                     TCB+specific[0] must point at TCB+specific_1stblock
    rseq_cpu_id      __rseq_offset + 4 (struct rseq.cpu_id); inside struct
                     pthread; the calling thread's cpu_id >= 0 if registered
    cleanup          _thread_db_pthread_cancelhandling - 16 (the cleanup and
                     cleanup_jmp_buf pointers precede cancelhandling); must be
                     robust_head + 24 (right after struct robust_list_head)
  libc TLS:
    resp_tls         dlvsym("__resp", GLIBC_PRIVATE) - TCB; initial-exec, so
                     below the TCB; main thread: holds &_res; other threads:
                     points into their own struct pthread (start_thread)
  Needed symbols: _dl_allocate_tls, _dl_deallocate_tls (GLIBC_PRIVATE).

  glibc 2.36 condvars (nptl/pthread_cond_wait.c; what condvar repair rests
  on), probed on a live pthread blocked in pthread_cond_wait
  (cg_probe_condwait):
    cond_cleanup     while blocked, TCB+cleanup points at a cleanup record on
                     the waiter's stack; its routine (this address, inside
                     libc.so) is glibc's cancellation cleanup for condvar
                     waiters, its argument {wseq, cond, mutex, private}
                     (repair.h struct cg_cond_cbuf) names our condvar and
                     mutex, wseq + 2 == cond.__wseq, and the waiter holds one
                     reference on its group (cond.__g_refs[wseq & 1] == 2);
                     once the wait returns TCB+cleanup is what it was before.
  CPython 3.11 GIL (Include/internal/pycore_gil.h, Python/ceval_gil.h; what
  GIL repair rests on).  gilrepair.c (and lastresort.c, for
  _Py_DumpTracebackThreads) is compiled against the internal headers;
  cg_gil_probe checks them against the running interpreter:
    the interpreter is the exact release the headers are (PY_VERSION_HEX ==
    Py_Version) and sizeof(_PyRuntimeState) equals the ELF size of the
    _PyRuntime symbol; holding the GIL, gil.locked == 1 and gil.last_holder
    and gilstate.tstate_current are our thread state, whose native_thread_id
    is gettid() and thread_id pthread_self(); gil.mutex and gil.switch_mutex
    are default-kind glibc mutexes (kind 0: owner recorded, unlock checks no
    owner), both condvars process-private.  A child's thread state is made
    by _PyThreadState_Prealloc in the parent and bound in the child by
    setting thread_id/native_thread_id and _PyThreadState_SetCurrent (3.11's
    PyGILState TSS note): the same fields the probe checks.
  CPython 3.11 frames (Include/internal/pycore_frame.h; what crash reports
  rest on): a crashing child records its Python stack by following
  tstate->cframe->current_frame and _PyInterpreterFrame.previous, keeping
  f_code and the offset _PyInterpreterFrame_LASTI gives; the container
  writes the lines with PyCode_Addr2Line.  Checked on this thread: the
  chain gives sys._getframe()'s code objects, innermost first, and the
  innermost offset lies on the calling line.
  CPython 3.11 interpreter state (Include/internal/pycore_gc.h,
  pycore_interp.h; what interp.c rests on: the collector on the
  container's thread, and what is mended after a death with the GIL):
    gcstate.generations[i].threshold/count are what gc.get_threshold() and
    gc.get_count() report; generation0 is generations[0].head; a tracked
    object's PyGC_Head is a ring of _gc_next/_gc_prev links whose low two
    prev bits are flags (checked on generation 0 both ways); the float,
    list, dict and key free lists are a count and an array or chain
    (counts checked within bounds).  Python's object allocator domains
    (MEM, OBJ) are set by the allocator guard before CPython starts
    (pyalloc.c): reported, not required (PYTHONMALLOC overrides it).
  glibc 2.36 plain mutexes (nptl/pthread_mutex_lock.c, lowlevellock.c; what
  the lock doctor, mutexes.c, rests on), probed on live pthreads blocked on
  a NORMAL, RECURSIVE, ERRORCHECK and ADAPTIVE mutex and in the relock after
  pthread_cond_wait of each (cg_probe_mutexwait), each read from outside through
  /proc/<tid>/syscall:
    mutex_wait_pc    every one waits in futex(&mutex.__lock, FUTEX_WAIT, 2)
                     at this one pc (__lll_lock_wait's call);
    mutex_ret_slot   the same word above sp holds a return address into libc,
    mutex_ret        one per kind (into pthread_mutex_lock by dladdr for the
                     four types): a waiter is a mutex's only when it returns
                     to one of these;
                     while held, __kind is the type and __owner the holder;
    private_wait_pc  a waiter in __lll_lock_wait_private (glibc's internal
                     locks) waits at a pc of its own;
  and on live pthreads blocked in pthread_mutex_timedlock (CLOCK_REALTIME)
  and pthread_mutex_clocklock (CLOCK_MONOTONIC) on a mutex of each type, and
  in each pthread_rwlock lock call ({wr,rd}lock, timed..., clock...) on a
  rwlock whose writer ended holding it, and in each wrlock call on a rwlock
  readers hold (cg_probe_timedwait):
    timed_wait_pc    every one waits in futex(word, FUTEX_WAIT_BITSET, v) at
                     this one pc (__futex_abstimed_wait64's call), v = 2 for
                     a mutex, its word the mutex's __lock; not mutex_wait_pc;
    timed_ret_slot   the word above sp where dladdr finds the return address
                     into each rwlock call, the same for all six; for the
                     timed mutexes (waiting at the same pc) the word there
                     lies in libc (their function is not exported),
    mutex_timed_ret  one per type, the same for timedlock and clocklock, none
                     a pthread_mutex_lock return or a rwlock's;
    rwlock_ret       one per rwlock call, and rwlock_futex_off the word it
                     waits on: __writers_futex for a writer on a writer,
                     __wrphase_futex for a reader on a writer and a writer
                     on readers; __cur_writer is the writer's tid (0 under
                     readers), and a
                     thread that writes its own tid there and calls
                     pthread_rwlock_unlock lets the waiter in (the release);
  a failure here leaves these waits unrecognized and says why
  (Report.timed_wait_unavailable); plain waits are still recognized.
  and the kernel's pid cursor (/proc/sys/kernel/ns_last_pid) is readable.
  These do not refuse isolation: they say why dead nodes' mutexes cannot be
  released (Report.mutex_repair_unavailable).
  Kernel: clone3 + CLONE_CLEAR_SIGHAND (5.5), CLONE_INTO_CGROUP (5.7),
  waitid(P_PIDFD) (5.4), pidfd_send_signal (5.1); probed as well.
"""

from __future__ import annotations

import os
import platform
import sys
import threading
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from types import FrameType
from typing import Any

SUPPORTED_MACHINES = ("x86_64",)
SUPPORTED_GLIBC = ("2.36",)
SUPPORTED_PYTHON = ((3, 11),)
MIN_KERNEL = (5, 7)

TCBHEAD = {
    "tcb": 0x00,
    "self": 0x10,
    "multiple_threads": 0x18,
    "stack_guard": 0x28,
    "pointer_guard": 0x30,
}
TCBHEAD_FEATURE_1 = 0x48
RSEQ_CPU_ID = 4  # offsetof(struct rseq, cpu_id), linux/rseq.h
PTHREAD_KEY_2NDLEVEL_SIZE = 32


class IsolationUnavailable(RuntimeError):
    """The platform is not one the isolated core is known to be sound on."""


@dataclass(frozen=True)
class Layout:
    """Byte offsets from the thread pointer; mirrors struct cg_layout."""

    tcb: int
    self: int
    multiple_threads: int
    stack_guard: int
    pointer_guard: int
    list: int
    tid: int
    robust_head: int
    specific: int
    specific_1stblock: int
    rseq_cpu_id: int
    resp_tls: int
    robust_futex_offset: int
    cleanup: int
    cond_cleanup: int
    mutex_wait_pc: int = 0
    mutex_ret_slot: int = 0
    mutex_ret: tuple[int, ...] = (0,) * 8
    private_wait_pc: int = 0
    timed_wait_pc: int = 0
    timed_ret_slot: int = 0
    mutex_timed_ret: tuple[int, ...] = (0,) * 4
    rwlock_ret: tuple[int, ...] = (0,) * 9
    rwlock_futex_off: tuple[int, ...] = (0,) * 9

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class Report:
    machine: str
    glibc: str
    python: str
    kernel: str
    layout: Layout
    checks: tuple[str, ...]
    notes: tuple[str, ...] = field(default=())
    # Why native mutexes of dead nodes cannot be released here ("": they can).
    mutex_repair_unavailable: str = ""
    # Why waits in pthread_mutex_timedlock/_clocklock and on a rwlock are not
    # recognized here ("": they are).
    timed_wait_unavailable: str = ""

    def __str__(self) -> str:
        head = f"isolation available: {self.machine}, glibc {self.glibc}, Python {self.python}, kernel {self.kernel}"
        return "\n".join([head, *("  ok   " + c for c in self.checks), *("  note " + n for n in self.notes)])


def _glibc_version() -> str:
    try:
        return (os.confstr("CS_GNU_LIBC_VERSION") or "").split()[1]
    except (ValueError, OSError, AttributeError, IndexError):
        return "none"


def _kernel_tuple(release: str) -> tuple[int, int]:
    parts = release.split(".")
    try:
        return int(parts[0]), int("".join(ch for ch in parts[1] if ch.isdigit()))
    except (IndexError, ValueError):
        return (0, 0)


def _task_count() -> int:
    try:
        return len(os.listdir("/proc/self/task"))
    except OSError:
        return threading.active_count()


class _Checker:
    """Collects passes and failures so one run names every problem."""

    def __init__(self) -> None:
        self.passed: list[str] = []
        self.failed: list[str] = []
        self.notes: list[str] = []

    def check(self, ok: bool, good: str, bad: str) -> bool:
        (self.passed.append(good) if ok else self.failed.append(bad))
        return ok


def core_module() -> tuple[Any, Any]:
    """The clone core's cffi module (ffi, lib), or IsolationUnavailable
    saying it is not built here."""
    try:
        from cloneguard.container.isolated._clonecore import ffi, lib
    except ImportError as e:
        raise IsolationUnavailable(f"C core not built: {e}") from e
    return ffi, lib


def self_check(
    *,
    glibc_version: str | None = None,
    python_version: tuple[int, int] | None = None,
    machine: str | None = None,
    kernel_release: str | None = None,
    overrides: Mapping[str, int] | None = None,
) -> Report:
    """Check the platform and discover the layout; raise if anything fails.

    Each keyword replaces what would be read from the running system (for
    tests).  ``overrides`` replaces discovered Layout values by name before
    they are checked, e.g. ``overrides={"tid": 724}``.
    """
    ck = _Checker()
    machine = machine or platform.machine()
    glibc = glibc_version or _glibc_version()
    pyver = tuple(python_version or sys.version_info[:2])
    kernel = kernel_release or platform.release()
    overrides = dict(overrides or {})
    unknown = set(overrides) - {f.name for f in fields(Layout)}
    if unknown:
        raise ValueError(f"unknown layout field(s) to override: {sorted(unknown)}")

    ck.check(
        machine in SUPPORTED_MACHINES,
        f"machine {machine}",
        f"machine {machine!r} is not supported (only {SUPPORTED_MACHINES})",
    )
    ck.check(
        glibc in SUPPORTED_GLIBC, f"glibc {glibc}", f"glibc version {glibc!r} is not supported (only {SUPPORTED_GLIBC})"
    )
    ck.check(
        sys.implementation.name == "cpython" and pyver in SUPPORTED_PYTHON,
        f"CPython {pyver[0]}.{pyver[1]}",
        f"Python {sys.implementation.name} {pyver[0]}.{pyver[1]} is not supported (only CPython {SUPPORTED_PYTHON})",
    )
    ck.check(
        _kernel_tuple(kernel) >= MIN_KERNEL,
        f"kernel {kernel}",
        f"kernel {kernel} is older than {MIN_KERNEL[0]}.{MIN_KERNEL[1]} "
        "(clone3 with CLONE_INTO_CGROUP/CLONE_CLEAR_SIGHAND, P_PIDFD)",
    )
    if ck.failed:  # no point reading memory with layouts we never checked
        raise IsolationUnavailable("; ".join(ck.failed))

    ffi, lib = core_module()

    err = lib.cg_probe_clone3()
    ck.check(err == 0, "clone3 syscall present", f"clone3 probe failed: {os.strerror(err)}")
    try:
        os.close(os.pidfd_open(os.getpid()))
        ck.passed.append("pidfd_open works")
    except (OSError, AttributeError) as e:
        ck.failed.append(f"pidfd_open failed: {e}")

    layout = _discover_and_verify(ck, ffi, lib, overrides)
    layout, mutex_unavailable = _probe_mutexwait(ck, ffi, lib, layout, overrides)
    layout, timed_unavailable = _probe_timedwait(ck, ffi, lib, layout, overrides)
    try:
        with open("/proc/sys/kernel/core_pattern") as f:
            pattern = f.read().strip()
        ck.notes.append(
            f"core_pattern {pattern!r}: children run with "
            "RLIMIT_CORE=1, which means no dump for file and pipe "
            "patterns alike"
        )
    except OSError:
        pass
    if ck.failed:
        raise IsolationUnavailable("; ".join(ck.failed))
    return Report(
        machine,
        glibc,
        f"{pyver[0]}.{pyver[1]}",
        kernel,
        layout,
        tuple(ck.passed),
        tuple(ck.notes),
        mutex_repair_unavailable=mutex_unavailable,
        timed_wait_unavailable=timed_unavailable,
    )


def check_multithreaded() -> None:
    """Raise unless glibc already treats the process as multi-threaded.

    clone3 children share the parent's malloc and stdio; glibc only takes its
    locks (and x86 atomics their lock prefix) once it knows of a second thread.
    Call after the monitor thread has started.
    """
    from cloneguard.container.isolated._clonecore import ffi, lib

    tp = lib.cg_thread_pointer()
    mt = ffi.cast("int32_t *", tp + TCBHEAD["multiple_threads"])[0]
    single = ffi.cast("char *", lib.cg_lookup(b"__libc_single_threaded", ffi.NULL))
    if mt != 1 or (single != ffi.NULL and single[0] != b"\0"):
        raise IsolationUnavailable(
            f"glibc still thinks the process is single-threaded "
            f"(multiple_threads={mt}) after the monitor thread started"
        )


def _probe_condwait(ck: _Checker, ffi: Any, lib: Any, L: Layout, overrides: dict) -> Layout:
    """A live pthread blocked in pthread_cond_wait, read from outside."""
    p = ffi.new("struct cg_condwait_probe *")
    if lib.cg_probe_condwait(L.cleanup, p) != 0:
        ck.failed.append("condvar probe: could not start its thread")
        return L
    where = f"offset cleanup={L.cleanup}"
    ok = ck.check(
        bool(p.found),
        f"cleanup @{L.cleanup} set while blocked in pthread_cond_wait",
        f"{where} does not hold: a thread blocked in pthread_cond_wait left it NULL",
    )
    if ok:
        ck.check(
            bool(p.buf_on_stack),
            "condvar cleanup record on the waiter's stack",
            f"{where} does not hold: it does not point at the waiter's stack",
        )
        ck.check(
            bool(p.cbuf_matches and p.wseq_matches),
            "condvar cleanup argument = {wseq, cond, mutex, private}",
            "glibc condvar waiter record is not {wseq, cond, mutex, private} naming the waiter's condvar and position",
        )
        ck.check(
            bool(p.holds_ref),
            "a blocked condvar waiter holds one group reference",
            "glibc condvar: a blocked waiter does not hold a __g_refs reference (not the 2.36 algorithm)",
        )
        ck.check(
            bool(p.routine_in_libc),
            f"condvar cleanup routine {p.routine:#x} in libc",
            f"condvar cleanup routine {p.routine:#x} is not inside libc.so",
        )
        ck.check(
            bool(p.cleared_after),
            "cleanup restored once the wait returns",
            f"{where}: still set after pthread_cond_wait returned",
        )
    routine = overrides.get("cond_cleanup", int(p.routine) if ok else 0)
    return Layout(**{**L.as_dict(), "cond_cleanup": routine})


MUTEX_TYPES = ("NORMAL", "RECURSIVE", "ERRORCHECK", "ADAPTIVE")
#: each type's plain lock, then its relock after pthread_cond_wait (probes.c)
MUTEX_WAITS = (*MUTEX_TYPES, *(f"{t} (relock after pthread_cond_wait)" for t in MUTEX_TYPES))
FUTEX_WAIT = 0
FUTEX_CMD_MASK = ~(128 | 256)  # FUTEX_PRIVATE_FLAG, FUTEX_CLOCK_REALTIME
PID_CURSOR = "/proc/sys/kernel/ns_last_pid"
MUTEX_NO_ELISION = 512  # PTHREAD_MUTEX_NO_ELISION_NP


def _probe_mutexwait(ck: _Checker, ffi: Any, lib: Any, L: Layout, overrides: dict) -> tuple[Layout, str]:
    """Live pthreads blocked on each kind of plain mutex, and on a
    glibc-internal lock, read from outside the way mutexes.c reads a
    waiter. A failure does not refuse isolation: it says why dead nodes'
    mutexes cannot be released here (the second value)."""
    failed: list[str] = []

    def check(ok: bool, good: str, bad: str) -> None:
        (ck.passed if ok else failed).append(good if ok else bad)

    try:
        with open(PID_CURSOR) as f:
            int(f.read())
        ck.passed.append(f"pid cursor readable ({PID_CURSOR})")
    except (OSError, ValueError) as e:
        failed.append(f"cannot read the pid cursor {PID_CURSOR} ({e}): a dead owner cannot be proven")
    p = ffi.new("struct cg_mutexwait_probe *")
    rc = lib.cg_probe_mutexwait(p)
    if rc < 0:
        failed.append(f"mutex waiter probe failed: {os.strerror(-rc)}")
    else:
        for k, name in enumerate(MUTEX_WAITS):
            where = f"a waiter on a {name} mutex"
            check(bool(p.seen[k]), f"{where} seen in futex()", f"{where} was not seen in futex(&mutex) within 2 s")
            if not p.seen[k]:
                continue
            check(
                p.op[k] & FUTEX_CMD_MASK == FUTEX_WAIT and p.val[k] == 2,
                f"{where}: FUTEX_WAIT for 2",
                f"{where} waits with futex op {p.op[k]:#x} value {p.val[k]}, not FUTEX_WAIT for 2",
            )
            check(
                p.pc[k] == p.pc[0],
                f"{where}: at pc {p.pc[k]:#x}",
                f"{where} waits at pc {p.pc[k]:#x}, not {p.pc[0]:#x} (__lll_lock_wait has one futex call)",
            )
            check(
                p.ret[k] != 0 and p.ret_slot[k] == p.ret_slot[0] and bool(p.ret_in_libc[k]),
                f"{where}: returns to {p.ret[k]:#x} (stack word {p.ret_slot[k]})",
                f"{where}: no return address into libc's lock function at stack word {p.ret_slot[0]}",
            )
            want = k % len(MUTEX_TYPES)  # glibc adds NO_ELISION (512) to a NORMAL set by attribute
            check(
                p.kind[k] & ~MUTEX_NO_ELISION == want and bool(p.owner_is_self[k]),
                f"{where}: __kind {p.kind[k]}, __owner = holder",
                f"{where}: __kind {p.kind[k]} (want type {want}) or __owner is not the holder's tid",
            )
        check(
            bool(p.private_seen) and p.private_val == 2 and p.private_pc not in (0, p.pc[0]),
            f"a waiter in __lll_lock_wait_private at pc {p.private_pc:#x}",
            "a waiter in __lll_lock_wait_private was not seen at a pc of its own",
        )
    values: dict[str, Any] = {
        "mutex_wait_pc": int(p.pc[0]) if not failed else 0,
        "mutex_ret_slot": int(p.ret_slot[0]) if not failed else 0,
        "mutex_ret": tuple(int(p.ret[k]) for k in range(len(MUTEX_WAITS))) if not failed else (0,) * len(MUTEX_WAITS),
        "private_wait_pc": int(p.private_pc) if not failed else 0,
    }
    values.update({k: v for k, v in overrides.items() if k in values})
    return Layout(**{**L.as_dict(), **values}), "; ".join(failed)


TIMED_CALLS = ("pthread_mutex_timedlock", "pthread_mutex_clocklock")
RWLOCK_CALLS = (
    "pthread_rwlock_wrlock",
    "pthread_rwlock_timedwrlock",
    "pthread_rwlock_clockwrlock",
    "pthread_rwlock_rdlock",
    "pthread_rwlock_timedrdlock",
    "pthread_rwlock_clockrdlock",
    "pthread_rwlock_wrlock",
    "pthread_rwlock_timedwrlock",
    "pthread_rwlock_clockwrlock",
)
FUTEX_WAIT_BITSET = 9
FUTEX_CLOCK_REALTIME = 256
TIMED_FIELDS = ("timed_wait_pc", "timed_ret_slot", "mutex_timed_ret", "rwlock_ret", "rwlock_futex_off")


def _probe_timedwait(ck: _Checker, ffi: Any, lib: Any, L: Layout, overrides: dict) -> tuple[Layout, str]:
    """Live pthreads blocked in the timed mutex locks and in the rwlock lock
    calls, read from outside the way mutexes.c reads a waiter. Needs the
    plain waits' layout (mutex_wait_pc) to tell them apart. A failure does
    not refuse isolation nor the plain waits: it says why these waits are
    not recognized (the second value), and they are not."""
    failed: list[str] = []

    def check(ok: bool, good: str, bad: str) -> None:
        (ck.passed if ok else failed).append(good if ok else bad)

    p = ffi.new("struct cg_timedwait_probe *")
    rc = lib.cg_probe_timedwait(p)
    if not L.mutex_wait_pc:
        failed.append("plain mutex waits are not recognized here")
    elif rc < 0:
        failed.append(f"timed waiter probe failed: {os.strerror(-rc)}")
    else:
        pc, slot = int(p.rw_pc[0]), int(p.rw_ret_slot[0])
        for k, call in enumerate(RWLOCK_CALLS):
            where = f"a waiter in {call} on a {'read' if k >= 6 else 'write'}-locked rwlock"
            check(bool(p.rw_seen[k]), f"{where} seen in futex()", f"{where} was not seen in futex(&rwlock) within 2 s")
            if not p.rw_seen[k]:
                continue
            # a writer waits for a writer on __writers_futex; a reader for a
            # writer, and a writer for readers, on __wrphase_futex
            want_off = p.off_writers_futex if k < 3 else p.off_wrphase_futex
            check(
                p.rw_op[k] & FUTEX_CMD_MASK == FUTEX_WAIT_BITSET and p.rw_futex_off[k] == want_off,
                f"{where}: FUTEX_WAIT_BITSET on rwlock+{p.rw_futex_off[k]}",
                f"{where} waits with futex op {p.rw_op[k]:#x} on rwlock+{p.rw_futex_off[k]}, "
                f"not FUTEX_WAIT_BITSET on rwlock+{want_off}",
            )
            check(
                p.rw_pc[k] == pc and pc not in (0, L.mutex_wait_pc, L.private_wait_pc),
                f"{where}: at pc {p.rw_pc[k]:#x}",
                f"{where} waits at pc {p.rw_pc[k]:#x}, not one pc of its own shared by every rwlock and timed wait",
            )
            check(
                p.rw_ret[k] != 0 and p.rw_ret_slot[k] == slot,
                f"{where}: returns to {p.rw_ret[k]:#x} (stack word {p.rw_ret_slot[k]})",
                f"{where}: no return address into {call} at stack word {slot}",
            )
            check(
                bool(p.rw_writer_recorded[k]) and bool(p.rw_released[k]),
                f"{where}: __cur_writer = the writer (0 under readers); released as mutexes.c does",
                f"{where}: __cur_writer was not the writer (0 under readers), or taking its place there and "
                "calling pthread_rwlock_unlock did not let the waiter in",
            )
        plain = set(L.mutex_ret)
        for k in range(2 * len(MUTEX_TYPES)):
            call, name = TIMED_CALLS[k % 2], MUTEX_TYPES[k // 2]
            where = f"a waiter in {call} on a {name} mutex"
            check(bool(p.seen[k]), f"{where} seen in futex()", f"{where} was not seen in futex(&mutex) within 2 s")
            if not p.seen[k]:
                continue
            realtime = FUTEX_CLOCK_REALTIME if k % 2 == 0 else 0
            check(
                p.op[k] & FUTEX_CMD_MASK == FUTEX_WAIT_BITSET
                and p.op[k] & FUTEX_CLOCK_REALTIME == realtime
                and p.val[k] == 2,
                f"{where}: FUTEX_WAIT_BITSET for 2",
                f"{where} waits with futex op {p.op[k]:#x} value {p.val[k]}, not FUTEX_WAIT_BITSET for 2"
                f"{' on CLOCK_REALTIME' if realtime else ''}",
            )
            check(p.pc[k] == pc, f"{where}: at pc {p.pc[k]:#x}", f"{where} waits at pc {p.pc[k]:#x}, not {pc:#x}")
            check(
                p.ret[k] != 0
                and bool(p.ret_in_libc[k])
                and p.ret[k] == p.ret[k & ~1]
                and p.ret[k] not in plain
                and p.ret[k] not in set(p.rw_ret),
                f"{where}: returns to {p.ret[k]:#x} (stack word {p.ret_slot[k]})",
                f"{where}: stack word {slot} ({p.ret[k]:#x}) is not a return address into libc of its own, "
                "the same for timedlock and clocklock",
            )
            want = k // 2
            check(
                p.kind[k] & ~MUTEX_NO_ELISION == want and bool(p.owner_is_self[k]),
                f"{where}: __kind {p.kind[k]}, __owner = holder",
                f"{where}: __kind {p.kind[k]} (want type {want}) or __owner is not the holder's tid",
            )
    values: dict[str, Any] = {
        "timed_wait_pc": int(p.rw_pc[0]),
        "timed_ret_slot": int(p.rw_ret_slot[0]),
        "mutex_timed_ret": tuple(int(p.ret[2 * t]) for t in range(4)),
        "rwlock_ret": tuple(int(r) for r in p.rw_ret),
        "rwlock_futex_off": tuple(int(o) for o in p.rw_futex_off),
    }
    if failed:  # refuse to guess: none of these waits is recognized
        values = {name: getattr(Layout, name) for name in TIMED_FIELDS}
    values.update({k: v for k, v in overrides.items() if k in values})
    return Layout(**{**L.as_dict(), **values}), "; ".join(failed)


def _probe_py_stack(ck: _Checker, ffi: Any, lib: Any) -> None:
    """crash.c records a crashing child's Python frames by following the
    thread state's frame chain (gilrepair.c cg_record_py_stack): here it
    must give this thread's frames, innermost first, at their lines."""
    here = sys._getframe()
    chain = []
    f: FrameType | None = here
    while f is not None:
        chain.append(f)
        f = f.f_back
    codes, lasti, more = ffi.new("void *[]", 128), ffi.new("int[]", 128), ffi.new("int *")
    n = lib.cg_record_py_stack(codes, lasti, 128, more)
    line = here.f_lineno - 1  # the line that made the call
    recorded = [int(ffi.cast("uintptr_t", codes[i])) for i in range(n)]
    at = [ln for start, end, ln in here.f_code.co_lines() if n and start <= lasti[0] * 2 < end]
    ok = recorded == [id(x.f_code) for x in chain[: len(recorded)]] and n == min(len(chain), 128) and at == [line]
    ck.check(
        ok,
        f"the frame chain crash reports follow gives this thread's {n} Python frames",
        f"cg_record_py_stack gave {n} frames {recorded[:3]}..., expected {len(chain)} "
        f"{[id(x.f_code) for x in chain[:3]]}... (line {at} for {line})",
    )


def _probe_gil(ck: _Checker, ffi: Any, lib: Any) -> None:
    """gilrepair.c's compiled view of the GIL against the running one."""
    g = ffi.new("struct cg_gil_probe *")
    lib.cg_gil_probe(g)
    ck.check(
        g.compiled_hex == g.running_hex,
        f"CPython internals built for the running {g.running_hex:#x}",
        f"gilrepair.c was built for CPython {g.compiled_hex:#x}, running {g.running_hex:#x}: rebuild the core",
    )
    ck.check(
        g.runtime_size_compiled == g.runtime_size_elf,
        f"sizeof(_PyRuntimeState) {g.runtime_size_compiled} == ELF size of _PyRuntime",
        f"_PyRuntimeState is {g.runtime_size_compiled} bytes in the headers, {g.runtime_size_elf} in the interpreter",
    )
    held = bool(g.locked == 1 and g.last_holder_is_me and g.tstate_current_is_me)
    ck.check(
        held,
        "GIL held: locked == 1, last_holder and tstate_current are ours",
        f"CPython GIL layout does not hold: with the GIL held, locked={g.locked}, "
        f"last_holder ours={bool(g.last_holder_is_me)}, tstate_current ours="
        f"{bool(g.tstate_current_is_me)}",
    )
    ck.check(
        bool(g.native_id_ok and g.thread_id_ok),
        "PyThreadState native_thread_id/thread_id = gettid()/pthread_self()",
        "PyThreadState.native_thread_id/thread_id do not hold gettid()/pthread_self()",
    )
    ck.check(
        g.mutex_kind == 0 and g.switch_mutex_kind == 0,
        "GIL mutexes are default-kind glibc mutexes",
        f"GIL mutex kinds {g.mutex_kind}/{g.switch_mutex_kind}, expected 0/0",
    )
    ck.check(
        (g.cond_wrefs_flags & 1) == 0 and (g.switch_cond_wrefs_flags & 1) == 0,
        "GIL condvars are process-private",
        "a GIL condvar is process-shared",
    )


def _probe_interp(ck: _Checker, ffi: Any, lib: Any) -> None:
    """interp.c's compiled view of the collector and free lists against the
    running interpreter (the release itself: _probe_gil)."""
    import gc

    p = ffi.new("struct cg_interp_probe *")
    lib.cg_interp_probe(p)
    ck.check(
        tuple(p.threshold) == gc.get_threshold(),
        "gc generations' thresholds read where gc.get_threshold() has them",
        f"gc thresholds read as {tuple(p.threshold)}, gc.get_threshold() says {gc.get_threshold()}",
    )
    ck.check(
        bool(p.generation0_is_head),
        "gc.generation0 is generations[0]'s head",
        "the collector's generation0 is not generations[0]'s head",
    )
    ck.check(
        bool(p.young_links_ok),
        "generation 0: next and prev links agree both ways",
        "generation 0's links do not read as a doubly linked ring",
    )
    ck.check(
        bool(p.free_lists_ok),
        "free-list counts (float, list, dict) within their bounds",
        "the free-list counts read out of their bounds: another layout",
    )


class _Memory:
    """Reads of the calling thread's memory and glibc's symbols, through the core."""

    def __init__(self, ffi: Any, lib: Any) -> None:
        self.ffi, self.lib = ffi, lib

    def u64(self, addr: int) -> int:
        return int(self.ffi.cast("uint64_t *", addr)[0])

    def i64(self, addr: int) -> int:
        return int(self.ffi.cast("int64_t *", addr)[0])

    def i32(self, addr: int) -> int:
        return int(self.ffi.cast("int32_t *", addr)[0])

    def u32(self, addr: int) -> int:
        return int(self.ffi.cast("uint32_t *", addr)[0])

    def sym(self, name: str, version: str | None) -> int:
        p = self.lib.cg_lookup(name.encode(), version.encode() if version else self.ffi.NULL)
        return int(self.ffi.cast("uintptr_t", p))

    def desc(self, name: str) -> tuple[int, int, int]:
        """nptl_db descriptor: (bits per element, element count, offset)."""
        a = self.sym(name, "GLIBC_PRIVATE")
        if not a:
            raise IsolationUnavailable(f"glibc symbol {name} not found")
        p = self.ffi.cast("uint32_t *", a)
        return int(p[0]), int(p[1]), int(p[2])


@dataclass
class _Thread:
    """The calling thread, as the verification reads it: its thread pointer
    (tp), the size of its struct pthread, what the kernel has as its robust
    list head."""

    ck: _Checker
    mem: _Memory
    tp: int
    sizeof_pthread: int
    head: int

    def inside(self, name: str, off: int, width: int) -> bool:
        """Bounds first: a wrong offset must fail, not read wild memory."""
        if 0 <= off and off + width <= self.sizeof_pthread:
            return True
        self.ck.failed.append(f"offset {name}={off} lies outside struct pthread ({self.sizeof_pthread} bytes)")
        return False


def _discover_and_verify(ck: _Checker, ffi: Any, lib: Any, overrides: dict) -> Layout:
    mem = _Memory(ffi, lib)
    for name in ("_dl_allocate_tls", "_dl_deallocate_tls"):
        ck.check(
            mem.sym(name, "GLIBC_PRIVATE") != 0,
            f"{name}@GLIBC_PRIVATE found",
            f"glibc symbol {name}@GLIBC_PRIVATE not found",
        )

    tp = int(lib.cg_thread_pointer())
    if not tp:
        raise IsolationUnavailable("arch_prctl(ARCH_GET_FS) gave no thread pointer")
    size_addr = mem.sym("_thread_db_sizeof_pthread", "GLIBC_PRIVATE")
    if not size_addr:
        raise IsolationUnavailable("glibc symbol _thread_db_sizeof_pthread not found")
    sizeof_pthread = mem.u32(size_addr)
    is_main = lib.cg_gettid() == os.getpid()

    head = int(lib.cg_robust_list_head())
    L = _discover(ck, mem, tp, head, overrides)
    t = _Thread(ck, mem, tp, sizeof_pthread, head)
    _verify_tcbhead(t, L)
    _verify_pthread(t, L)
    _verify_rseq(t, L)
    if t.inside("cleanup", L.cleanup, 8):
        ck.check(
            L.cleanup == L.robust_head + 24,
            f"cleanup @{L.cleanup} == robust_head + 24",
            f"offset cleanup={L.cleanup} is not robust_head+24 ({L.robust_head + 24})",
        )
        L = _probe_condwait(ck, ffi, lib, L, overrides)
    _probe_gil(ck, ffi, lib)
    _probe_interp(ck, ffi, lib)
    _probe_py_stack(ck, ffi, lib)
    _verify_resp(t, L, is_main)
    return L


def _discover(ck: _Checker, mem: _Memory, tp: int, head: int, overrides: dict) -> Layout:
    """The offsets, from glibc's nptl_db descriptors and symbols (then overrides)."""
    lib = mem.lib
    found: dict[str, Any] = dict(TCBHEAD)
    bits, n, tid = mem.desc("_thread_db_pthread_tid")
    ck.check(
        (bits, n) == (32, 1), "tid descriptor shape", f"_thread_db_pthread_tid describes {n}x{bits} bits, expected 1x32"
    )
    found["tid"] = tid
    bits, n, lst = mem.desc("_thread_db_pthread_list")
    ck.check(
        (bits, n) == (128, 1),
        "list descriptor shape",
        f"_thread_db_pthread_list describes {n}x{bits} bits, expected 1x128",
    )
    found["list"] = lst
    found["robust_head"] = head - tp if head else -1
    bits, n, spec = mem.desc("_thread_db_pthread_specific")
    # glibc describes it as one 2048-bit field; either shape is 32 pointers.
    ck.check(
        bits * n == 64 * PTHREAD_KEY_2NDLEVEL_SIZE,
        "specific descriptor shape",
        f"_thread_db_pthread_specific describes {n}x{bits} bits, expected 32 pointers",
    )
    found["specific"] = spec
    kd = mem.u32(mem.sym("_thread_db_sizeof_pthread_key_data", "GLIBC_PRIVATE"))
    found["specific_1stblock"] = spec - PTHREAD_KEY_2NDLEVEL_SIZE * kd
    rseq_off_addr = mem.sym("__rseq_offset", "GLIBC_2.35")
    found["rseq_cpu_id"] = (mem.i64(rseq_off_addr) + RSEQ_CPU_ID) if rseq_off_addr else -1
    resp = mem.sym("__resp", "GLIBC_PRIVATE")
    found["resp_tls"] = resp - tp if resp else 0
    found["robust_futex_offset"] = int(lib.cg_mutex_futex_offset())
    bits, n, cancel = mem.desc("_thread_db_pthread_cancelhandling")
    found["cleanup"] = cancel - 16
    found["cond_cleanup"] = 0  # filled in by the probe (_probe_condwait)
    found.update(overrides)
    return Layout(**{f.name: found[f.name] for f in fields(Layout) if f.name in found})


def _verify_tcbhead(t: _Thread, L: Layout) -> None:
    """tcbhead_t's fields, each against what it must hold."""
    ck, mem, tp = t.ck, t.mem, t.tp
    for name in ("tcb", "self"):
        off = getattr(L, name)
        if t.inside(name, off, 8):
            v = mem.u64(tp + off)
            ck.check(
                v == tp,
                f"tcbhead.{name} @{off:#x} == thread pointer",
                f"offset {name}={off:#x} does not hold: TCB+{off:#x} has {v:#x}, the thread pointer is {tp:#x}",
            )
    if t.inside("multiple_threads", L.multiple_threads, 4):
        v = mem.i32(tp + L.multiple_threads)
        want = (1,) if _task_count() > 1 else (0, 1)
        ck.check(
            v in want,
            f"multiple_threads @{L.multiple_threads:#x} = {v}",
            f"offset multiple_threads={L.multiple_threads:#x} does not hold: value {v}, expected one of {want}",
        )
    for name in ("stack_guard", "pointer_guard"):
        off = getattr(L, name)
        if t.inside(name, off, 8):
            ck.check(
                mem.u64(tp + off) != 0, f"{name} @{off:#x} set", f"offset {name}={off:#x} does not hold: value is 0"
            )
    f1 = mem.i32(tp + TCBHEAD_FEATURE_1)
    ck.check(f1 == 0, "CET (tcbhead.feature_1) off", f"CET is active (tcbhead.feature_1={f1:#x}); not supported")


def _verify_pthread(t: _Thread, L: Layout) -> None:
    """struct pthread's tid, list, robust list head and specific blocks."""
    ck, mem, tp, head = t.ck, t.mem, t.tp, t.head
    if t.inside("tid", L.tid, 4):
        v, me = mem.i32(tp + L.tid), int(mem.lib.cg_gettid())
        ck.check(
            v == me,
            f"tid @{L.tid} == gettid() ({me})",
            f"offset tid={L.tid} does not hold: TCB+{L.tid} has {v}, gettid() is {me}",
        )
    if t.inside("list", L.list, 16):
        nxt = mem.u64(tp + L.list)
        ok = nxt != 0 and mem.u64(nxt + 8) == tp + L.list
        ck.check(
            ok,
            f"list @{L.list}: list.next->prev == &list",
            f"offset list={L.list} does not hold: TCB+{L.list} is not a linked list_t",
        )
    if t.inside("robust_head", L.robust_head, 24):
        ck.check(
            head == tp + L.robust_head,
            f"robust_head @{L.robust_head} == get_robust_list(0)",
            f"offset robust_head={L.robust_head} does not hold: the kernel has {head - tp} (get_robust_list)",
        )
        ck.check(
            L.robust_head == L.tid + 16,
            "robust_head == tid + 16",
            f"offset robust_head={L.robust_head} is not tid+16 ({L.tid + 16})",
        )
        fo = mem.i64(tp + L.robust_head + 8)
        ck.check(
            fo == L.robust_futex_offset,
            f"robust futex_offset {fo} == pthread_mutex_t layout",
            f"robust_futex_offset={L.robust_futex_offset} does not hold: glibc registered {fo}",
        )
    if t.inside("specific", L.specific, 8) and t.inside(
        "specific_1stblock", L.specific_1stblock, PTHREAD_KEY_2NDLEVEL_SIZE * 16
    ):
        v = mem.u64(tp + L.specific)
        ck.check(
            v == tp + L.specific_1stblock,
            f"specific[0] @{L.specific} -> specific_1stblock @{L.specific_1stblock}",
            f"offset specific={L.specific}/specific_1stblock="
            f"{L.specific_1stblock} does not hold: specific[0] is "
            f"{v:#x}, expected {tp + L.specific_1stblock:#x}",
        )


def _verify_rseq(t: _Thread, L: Layout) -> None:
    """rseq's cpu_id: a CPU number where glibc registered rseq, else unregistered."""
    ck, mem = t.ck, t.mem
    if not t.inside("rseq_cpu_id", L.rseq_cpu_id, 4):
        return
    rseq_size_addr = mem.sym("__rseq_size", "GLIBC_2.35")
    registered = rseq_size_addr and mem.u32(rseq_size_addr) > 0
    cpu = mem.i32(t.tp + L.rseq_cpu_id)
    if registered:
        ck.check(
            0 <= cpu < 65536,
            f"rseq cpu_id @{L.rseq_cpu_id} = {cpu}",
            f"offset rseq_cpu_id={L.rseq_cpu_id} does not hold: value {cpu} is not a CPU number",
        )
    else:
        ck.notes.append("rseq not registered by glibc (tunable?)")
        ck.check(
            cpu in (-1, -2),
            f"rseq cpu_id @{L.rseq_cpu_id} unregistered",
            f"offset rseq_cpu_id={L.rseq_cpu_id} does not hold: {cpu}",
        )


def _verify_resp(t: _Thread, L: Layout, is_main: bool) -> None:
    """__resp: in the static TLS, pointing at _res (main thread) or into the thread's struct pthread."""
    ck, mem, tp = t.ck, t.mem, t.tp
    ck.check(
        -65536 < L.resp_tls < 0,
        f"__resp in static TLS ({L.resp_tls})",
        f"offset resp_tls={L.resp_tls} is not in the static TLS below the TCB",
    )
    if -65536 < L.resp_tls < 0:
        v = mem.u64(tp + L.resp_tls)
        if is_main:
            ok, wanted = v == mem.sym("_res", "GLIBC_2.2.5"), "&_res"
        else:
            ok, wanted = tp < v < tp + t.sizeof_pthread, "this thread's struct pthread"
        ck.check(
            ok,
            f"__resp @{L.resp_tls} -> {wanted}",
            f"offset resp_tls={L.resp_tls} does not hold: value {v:#x} is not {wanted}",
        )
