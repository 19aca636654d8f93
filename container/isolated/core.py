"""CloneCore: spawn clone3(CLONE_VM) children that run a Python callable.

Data flow: spawn() hands a request to the C monitor thread, which clones and
watches the child's pidfd; when the child dies (or asks to stop) the monitor
writes a record to a pipe; the listener thread here reads it and calls
``on_event``.  The monitor never takes the GIL; the listener blocks in
os.read with the GIL released.

    core = CloneCore(on_event=print)
    child = core.spawn(work)          # work() runs in the child
    core.kill(child, signal.SIGTERM)  # or core.request_stop(child)
    death = core.wait(child, timeout=5)
    core.release(child)               # frees stack, TLS, pidfd
    core.close()

Inside a child, ``stop_requested()`` tells whether it was asked to stop, and
``wait_for_go()`` waits, off the GIL, for the parent's ``core.go(child)``.

What the core does about a child's death is switchable (``Mitigations``), so
the harness can measure what each measure buys:

    core = CloneCore(on_event=print, gil_repair=False)
    core = CloneCore(mitigations=Mitigations(jemalloc_arena="auto"))
"""

from __future__ import annotations

import atexit
import errno
import itertools
import os
import signal
import sys
import threading
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any, Literal, overload

from cloneguard.container import locks
from cloneguard.container.isolated import assumptions, memory_watch, pybind11_registry
from cloneguard.container.isolated.assumptions import IsolationUnavailable
from cloneguard.container.isolated.collector import Collector
from cloneguard.container.isolated.core_dumps import Tools as DumpTools
from cloneguard.container.isolated.core_events import (
    KIND_CLOSED,
    KIND_DEATH,
    KIND_MUTEX,
    RECORD_SIZE,
    CoreEvent,
    Death,
    PkeyFault,
    Repair,
    StopRequested,
    decode,
)
from cloneguard.container.isolated.crash_reports import CrashStacks
from cloneguard.container.isolated.memory_watch import MemoryLimit

if TYPE_CHECKING:
    from cloneguard_interfaces.msg import ComponentEvent

__all__ = [
    "CloneCore",
    "Child",
    "Death",
    "StopRequested",
    "CoreEvent",
    "Repair",
    "Mitigations",
    "IsolationUnavailable",
    "stop_requested",
    "wait_for_go",
    "in_child",
    "allocator",
    "thread_arena",
    "thread_tcache",
]

DEFAULT_STACK = 8 << 20


@dataclass(frozen=True)
class Mitigations:
    """What the core does for the survivors of a child's death, and in it.

    gil_repair
        After a death, before it is reported, the monitor releases the GIL
        (and gil->mutex / gil->switch_mutex) if the dead task held it
        (gilrepair.c).  Off: a child dying with the GIL freezes the process.
    condvar_repair
        ... and cancels the dead task's wait on the GIL's condition
        variables (glibc's own cancellation cleanup), clearing a condvar
        lock it died holding.  Off: a child killed while waiting for the GIL
        can hang the next thread that signals the GIL condvar.
    interp_repair
        ... and when the dead task held the GIL, what it may have left
        half-done in the interpreter is mended before anyone else runs
        Python (interp.c: objects it was changing put out of the garbage
        collector's sight, GC links, free lists).  Off: the next collection
        can follow what it left half-written.
    crash_report
        A child that gets SIGSEGV/SIGBUS/SIGILL/SIGFPE/SIGABRT writes one
        report (signal, fault address, pc, native and Python stacks) to
        fd 2 from its own signal stack, then dies of that signal as before.
    jemalloc_arena
        With jemalloc as the malloc (LD_PRELOAD): "own" gives each child an
        arena of its own (arenas.create + thread.arena), "auto" leaves
        jemalloc's choice.  No effect on glibc malloc.
    jemalloc_tcache
        False turns the child's jemalloc thread cache off.
    container_gc
        Automatic garbage collection is off while the core is open; a thread
        of the container collects when CPython would have (collector.py), so
        no child is ever killed in the middle of a collection.  Off: CPython
        collects on whichever thread allocates, children included.
    alloc_guard
        The allocator guard (allocguard.c, preloaded with LD_PRELOAD): each
        child allocates from arenas of its own, set up by the container;
        blocks freed by anyone else are handed back to their owner instead
        of being freed into its arena; a child that dies inside the
        allocator has its arena quarantined.  None (default): on when the
        guard is preloaded.  With it, ``jemalloc_arena``/``jemalloc_tcache``
        do not apply (every child has its own arena and cache anyway).
    mutex_repair
        The lock doctor (mutexes.c): a plain pthread mutex whose owner was a
        task of a dead child, and that a live task is blocked on, is
        released, and reported (MutexReport); what it cannot prove or must
        not touch is reported, not touched.  None (default): on where the
        platform checks allow (assumptions.py), True: required there.
    pybind11_ahead
        pybind11's registry of live instances is rehashed on the container's
        threads before a child's insert would have to (pybind11_registry.py),
        so that no child is killed in the middle of a rehash.  None
        (default): on where its check passes, True: required.
    """

    gil_repair: bool = True
    condvar_repair: bool = True
    interp_repair: bool = True
    crash_report: bool = True
    jemalloc_arena: Literal["own", "auto"] = "own"
    jemalloc_tcache: bool = True
    container_gc: bool = True
    alloc_guard: bool | None = None
    mutex_repair: bool | None = None
    pybind11_ahead: bool | None = None

    def __post_init__(self) -> None:
        if self.jemalloc_arena not in ("own", "auto"):
            raise ValueError(f"jemalloc_arena must be 'own' or 'auto', not {self.jemalloc_arena!r}")

    def as_config(self) -> dict[str, int]:
        """struct cg_config."""
        return {
            "gil_repair": int(self.gil_repair),
            "condvar_repair": int(self.condvar_repair),
            "interp_repair": int(self.interp_repair),
            "crash_report": int(self.crash_report),
            "jemalloc_own_arena": int(self.jemalloc_arena == "own"),
            "jemalloc_tcache": int(self.jemalloc_tcache),
            "alloc_guard": int(bool(self.alloc_guard)),
            "mutex_repair": int(bool(self.mutex_repair)),
        }


@dataclass(frozen=True)
class DeadFrames:
    """The words a dead task's Python frames hold (CloneCore.dead_frame_refs):
    references for certain; words its innermost frame holds that may point
    at what its last instruction was changing; and that frame's (code
    object address, instruction offset in code units, value stack words)
    where it was running whole, else None."""

    known: list[int]
    maybe: list[int]
    running: tuple[int, int, list[int]] | None


@dataclass(frozen=True)
class Child:
    pid: int
    pidfd: int
    serial: int
    start_time_ns: int  # CLOCK_MONOTONIC at clone
    stack_size: int
    cgroup_fd: int | None
    _block: Any = field(default=None, repr=False, compare=False)


class _Entry:
    """CloneCore's bookkeeping for one child: guarded by CloneCore._lock, and
    waited on with CloneCore._changed (plain flags, not an Event each: a
    spawn makes one, and it is on the spawn's path)."""

    __slots__ = ("target", "child", "spawned", "dead", "death_reported", "death")

    def __init__(self, target: Callable[[], object]) -> None:
        self.target: Callable[[], object] | None = target  # alive until reaped
        self.child: Any = None  # the Child, once spawn() has it
        self.spawned = False  # spawn() has returned (or failed)
        self.dead = False  # reaped; death is set
        self.death_reported = False  # on_event has returned for the death
        self.death: Death | None = None

    def is_dead(self) -> bool:
        return self.dead

    def death_was_reported(self) -> bool:
        return self.death_reported


def _lib() -> tuple[Any, Any]:
    from cloneguard.container.isolated._clonecore import ffi, lib

    return ffi, lib


def stop_requested() -> bool:
    """Inside a child: has it been asked to stop (SIGTERM or the parent)?"""
    _, lib = _lib()
    s = lib.cg_self_stop_requested()
    if s < 0:
        raise RuntimeError("stop_requested() called outside an isolated child")
    return s != 0


def wait_for_go() -> bool:
    """Inside a child: wait, off the GIL, for the parent's next
    ``CloneCore.go`` (each go lets one wait through, and one given before
    the wait is not lost), or until it is asked to stop (by the parent or a
    signal), which ends every wait. True if it is to stop."""
    _, lib = _lib()
    s = lib.cg_self_wait_go()
    if s < 0:
        raise RuntimeError("wait_for_go() called outside an isolated child")
    return s != 0


def in_child() -> bool:
    """Is the calling code running in a clone child?"""
    _, lib = _lib()
    return lib.cg_self_stop_requested() >= 0


def allocator() -> str:
    """The process's malloc: "glibc" or "jemalloc <version>"."""
    ffi, lib = _lib()
    buf = ffi.new("char[128]")
    lib.cg_allocator(buf, 128)
    name = ffi.string(buf).decode()
    return name.split("-", 1)[0] if name.startswith("jemalloc") else name


def thread_arena() -> int | None:
    """The jemalloc arena the calling thread allocates from (None without
    jemalloc).  In a child with jemalloc_arena="own", one of its own."""
    _, lib = _lib()
    a = lib.cg_jemalloc_thread_arena()
    return None if a < 0 else a


def thread_tcache() -> bool | None:
    """Whether the calling thread has a jemalloc thread cache (None without
    jemalloc)."""
    _, lib = _lib()
    t = lib.cg_jemalloc_thread_tcache()
    return None if t < 0 else bool(t)


def _resolve_guard(m: Mitigations) -> Mitigations:
    """alloc_guard None -> whether the guard is preloaded; True where it
    cannot work -> IsolationUnavailable."""
    from cloneguard.container import allocator

    loaded = allocator.guard_loaded()
    if m.alloc_guard is None:
        m = replace(m, alloc_guard=loaded)
    if not m.alloc_guard:
        return m
    if not loaded:
        raise IsolationUnavailable(f"the allocator guard is not preloaded (LD_PRELOAD={allocator.GUARD_PATH})")
    if not allocator.jemalloc_active() and not allocator.own_arenas():
        raise IsolationUnavailable(
            "the allocator guard under glibc malloc needs an arena per task: call "
            "cloneguard.container.allocator.glibc_arena_per_task() before a second thread starts"
        )
    return m


def _where_possible(m: Mitigations, name: str, why: str | None, cannot: str, without: str) -> Mitigations:
    """A mitigation that is on where possible: ``why`` says why it is not
    possible here (None: it is). None -> possible or not, said on stderr
    (``without``) when not; True where impossible -> IsolationUnavailable."""
    wanted = getattr(m, name)
    if wanted and why:
        raise IsolationUnavailable(f"{cannot}: {why}")
    if wanted is None:
        if why:
            print(f"cloneguard: {without}: {why}", file=sys.stderr)
        changes: dict[str, Any] = {name: not why}
        m = replace(m, **changes)
    return m


def _resolve_mutex_repair(m: Mitigations, report: assumptions.Report) -> Mitigations:
    """mutex_repair: on where the platform checks allow it. Where it is on
    but the timed waits' checks failed, says so on stderr: a waiter in
    pthread_mutex_timedlock/_clocklock or on a rwlock is then not seen."""
    m = _where_possible(
        m,
        "mutex_repair",
        report.mutex_repair_unavailable,
        "native mutex repair is not possible here",
        "dead nodes' native mutexes will not be released",
    )
    if m.mutex_repair and report.timed_wait_unavailable:
        print(
            "cloneguard: a dead node's native mutex will not be released, nor reported, for a task waiting in "
            f"pthread_mutex_timedlock/_clocklock, nor its rwlock: {report.timed_wait_unavailable}",
            file=sys.stderr,
        )
    return m


def _resolve_pybind11_ahead(m: Mitigations) -> Mitigations:
    """pybind11_ahead: on where its check passes."""
    return _where_possible(
        m,
        "pybind11_ahead",
        pybind11_registry.unavailable() if m.pybind11_ahead is not False else None,
        "pybind11's instance registry cannot be kept ahead",
        "a node killed while pybind11 rehashes can end the container",
    )


class CloneCore:
    """The process's one clone3 spawner and monitor.

    ``on_event`` is called from the listener thread with each Death and
    StopRequested, in the order the monitor saw them (a child's
    StopRequested always precedes its Death).  Exceptions it raises are
    printed and otherwise ignored.  It should return promptly: while it runs
    no other event is delivered, and after ~2000 undelivered records the
    monitor (and so spawn) waits.  It must not call close().

    Only one may be open per process (there is one C monitor).  An open core
    is kept alive by the class until close(); atexit closes it.

    ``mitigations`` (default: all on, own jemalloc arenas) and keyword
    overrides of its fields, e.g. ``CloneCore(gil_repair=False)``, fix what
    the core does for this core's lifetime (``self.mitigations``).
    """

    _instance_lock = threading.Lock()
    _open: CloneCore | None = None

    def __init__(
        self,
        on_event: Callable[[CoreEvent], None] | None = None,
        mitigations: Mitigations | None = None,
        stop_signal: int = 0,
        dump_tools: DumpTools | None = None,
        memory_watch: tuple[MemoryLimit, int] | None = None,
        **overrides: Any,
    ) -> None:
        names = {f.name for f in fields(Mitigations)}
        unknown = set(overrides) - names
        if unknown:
            raise TypeError(f"unknown mitigation(s): {sorted(unknown)}; known: {sorted(names)}")
        self.mitigations = _resolve_guard(replace(mitigations or Mitigations(), **overrides))
        self.report = assumptions.self_check()
        self.mitigations = _resolve_mutex_repair(self.mitigations, self.report)
        self.mitigations = _resolve_pybind11_ahead(self.mitigations)
        self._keep_ahead = pybind11_registry.keep_ahead if self.mitigations.pybind11_ahead else None
        if self._keep_ahead is not None:
            self._keep_ahead()
        ffi, lib = _lib()
        self._event_fd = self._start_monitor(ffi, lib, stop_signal, dump_tools, memory_watch)
        self._on_event = on_event
        # _lock guards _entries, _closed, _spawning, and every use of a
        # child's block or pidfd (so none can race with release()).
        self._lock = threading.Lock()
        # Notified whenever _spawning or an entry's flags change.
        self._changed = threading.Condition(self._lock)
        self._entries: dict[int, _Entry] = {}
        self._serials = itertools.count(1)
        self._spawning = 0
        self._closed = False  # spawn refused
        self._stopped = False  # monitor stopped
        self._crash_stacks = CrashStacks(lib, ffi)
        try:
            assumptions.check_multithreaded()
        except IsolationUnavailable:
            self._shutdown_monitor()
            os.close(self._event_fd)
            raise
        self._listener = threading.Thread(target=self._listen, daemon=True, name="cloneguard-core-listener")
        self._listener.start()
        self._collector = Collector(ffi, lib, self._keep_ahead) if self.mitigations.container_gc else None
        # Python locks that know their holder (container/locks.py), where
        # boot.py installed them: every child that ends leaves its held
        # locks to be taken over.
        self._pylocks = None
        if locks.installed():
            import cloneguard.container.isolated._pylocks as _pylocks  # an extension module

            self._pylocks = _pylocks
            locks.activate()

    def _start_monitor(
        self,
        ffi: Any,
        lib: Any,
        stop_signal: int,
        dump_tools: DumpTools | None,
        memory_watch: tuple[MemoryLimit, int] | None,
    ) -> int:
        """Start the C monitor, the one of this process (one CloneCore may be
        open): the fd its events come on."""
        with CloneCore._instance_lock:
            if CloneCore._open is not None:
                raise RuntimeError("only one CloneCore may be open per process")
            fd = ffi.new("int *")
            layout = ffi.new("struct cg_layout *", self.report.layout.as_dict())
            # stop_signal: the test rig's stop points (seams.stop_signal);
            # dump_tools: the monitor has a crashing child dumped (dumps.c)
            # where name_dump() said.
            settings: dict[str, Any] = {"stop_signal": stop_signal}
            if dump_tools is not None:
                settings.update(core_dumps=1, gdb=dump_tools.gdb.encode(), fallocate=dump_tools.fallocate.encode())
            config = ffi.new("struct cg_config *", {**self.mitigations.as_config(), **settings})
            # memory_watch: (what the container may use, the margin below it
            # where the monitor ends the node process using the most).
            self._watch_fds = self._watch_memory(memory_watch)
            rc = lib.cg_start(layout, config, fd)
            if rc < 0:
                self._unwatch_memory()
                if rc == -errno.ENOTSUP:  # only the guard says so
                    raise OSError(
                        -rc,
                        "cannot start the allocator guard: glibc's per-thread malloc state (thread_arena, "
                        "tcache) is not in libc's TLS where glibc 2.36 keeps it (allocguard.c, find_glibc_tls)",
                    )
                raise OSError(-rc, f"cannot start the monitor: {os.strerror(-rc)}")
            CloneCore._open = self
        return fd[0]

    # -- children ---------------------------------------------------------
    def spawn(
        self,
        target: Callable[[], object],
        *,
        cgroup_fd: int | None = None,
        stack_size: int = DEFAULT_STACK,
        _allow_core_dump: bool = False,
    ) -> Child:
        """Run ``target()`` in a new child; return once its pid is known.

        Exit code 0 if target returns, 1 if it raises (traceback printed),
        n for SystemExit(n).  ``cgroup_fd``: a cgroup2 directory fd the child
        is born in.  ``_allow_core_dump`` is for experiments only: a dump
        writes the whole shared address space.
        """
        if not callable(target):
            raise TypeError("target must be callable")
        ffi, lib = _lib()
        entry = _Entry(target)
        with self._lock:
            if self._closed:
                raise RuntimeError("CloneCore is closed")
            serial = next(self._serials)
            self._entries[serial] = entry
            self._spawning += 1
        out = ffi.new("struct cg_child **")
        flags = lib.CG_FLAG_ALLOW_CORE if _allow_core_dump else 0
        if self._keep_ahead is not None:
            self._keep_ahead()
        try:
            # The child gets a borrowed pointer; entry.target keeps it alive.
            rc = lib.cg_spawn(
                ffi.cast("void *", id(target)), serial, stack_size, -1 if cgroup_fd is None else cgroup_fd, flags, out
            )
            if rc == -errno.EPERM:
                raise RuntimeError("spawn() from inside a child is not supported")
            if rc < 0:
                why = self._no_free_slot() if rc == -errno.ENOMEM else None
                raise OSError(-rc, f"spawn failed: {why or os.strerror(-rc)}")
            b = out[0]
            if self._pylocks is not None:  # before its death can be dispatched
                self._pylocks.node_born(b.pid)
            entry.child = Child(b.pid, b.pidfd, serial, b.start_ns, stack_size, cgroup_fd, b)
            return entry.child
        finally:
            with self._lock:
                if entry.child is None:
                    del self._entries[serial]
                self._spawning -= 1
                entry.spawned = True
                self._changed.notify_all()

    def request_stop(self, child: Child) -> bool:
        """Set the child's stop flag (no signal); True if it was not set."""
        _, lib = _lib()
        with self._lock:
            self._entry(child)
            return bool(lib.cg_request_stop(child._block))

    def go(self, child: Child) -> None:
        """Let the child's current or next ``wait_for_go`` through."""
        _, lib = _lib()
        with self._lock:
            self._entry(child)
            lib.cg_go(child._block)

    def kill(self, child: Child, sig: int = signal.SIGKILL) -> bool:
        """pidfd_send_signal; False if the child has already died."""
        with self._lock:
            if self._entry(child).dead:  # reported dead: a zombie until released
                return False
            try:
                signal.pidfd_send_signal(child.pidfd, sig)
                return True
            except ProcessLookupError:
                return False

    @overload
    def wait(self, child: Child) -> Death: ...
    @overload
    def wait(self, child: Child, timeout: float | None) -> Death | None: ...

    def wait(self, child: Child, timeout: float | None = None) -> Death | None:
        """The child's Death once reaped, or None on timeout."""
        with self._lock:
            entry = self._entry(child)
            self._changed.wait_for(lambda: entry.dead, timeout)
            return entry.death

    def release(self, child: Child) -> None:
        """Reap a dead child (the monitor reports a death and leaves the
        zombie to this) and free its thread state, stacks, TLS and pidfd (once).

        The thread state (made by spawn, so that the child never takes the
        interpreter's HEAD_LOCK) is unlinked before the stack is unmapped: a
        child killed inside Python leaves frames pointing into it.  Takes the
        GIL (given back by the monitor if the child died holding it).
        """
        _, lib = _lib()
        with self._lock:
            entry = self._entry(child)
            if not entry.dead:
                raise RuntimeError(f"child {child.pid} has not been reaped yet")
            del self._entries[child.serial]
            rc = lib.cg_release(child._block)
        if rc < 0:  # cannot happen once the death record was seen
            raise OSError(-rc, f"release failed: {os.strerror(-rc)}")

    def name_dump(self, child: Child, path: str) -> None:
        """With core dumps on: where the child's dump goes if it crashes
        (named again once its node's name is known). Too late once it died."""
        data = path.encode()
        ffi, lib = _lib()
        if len(data) >= lib.CG_CORE_PATH:
            raise ValueError(f"a core dump's path is too long: {path}")
        with self._lock:
            entry = self._entries.get(child.serial)
            if entry is not None and entry.child is child and not entry.dead:
                ffi.memmove(child._block.core_path, data + b"\0", len(data) + 1)

    def abandon(self, child: Child, hold_context: bool = False) -> None:
        """Forget a reaped child whose Python objects are to be kept (a
        crashed node the host leaves in memory): its thread state and stacks
        stay allocated, since its frames point into them; its TLS context
        goes back to the pool for the next child (unless its allocator slot
        is quarantined), or with ``hold_context`` only at ``give_back``
        (which must then come), and it is reaped and its pidfd closed."""
        _, lib = _lib()
        with self._lock:
            entry = self._entry(child)
            if not entry.dead:
                raise RuntimeError(f"child {child.pid} has not been reaped yet")
            del self._entries[child.serial]
            rc = lib.cg_abandon(child._block, int(hold_context))
        if rc < 0:
            raise OSError(-rc, f"abandon failed: {os.strerror(-rc)}")

    def dead_frame_refs(self, child: Child, room: int = 1 << 16) -> DeadFrames | None:
        """What a dead child's Python frames refer to (interp.c
        cg_dead_frame_refs says which words are which). Only for a child
        that was abandoned, not released. None if its frames could not be
        read whole."""
        ffi, lib = _lib()
        known, maybe = ffi.new("uintptr_t[]", room), ffi.new("uintptr_t[]", room)
        stack, top = ffi.new("uintptr_t[]", room), ffi.new("uintptr_t[3]")
        counts = ffi.new("int[2]")
        tstate = lib.cg_child_tstate(child._block)
        if lib.cg_dead_frame_refs(tstate, known, room, maybe, room, stack, room, top, counts) < 0:
            return None
        return DeadFrames(
            known=list(known[0 : counts[0]]),
            maybe=list(maybe[0 : counts[1]]),
            running=(top[0], top[1], list(stack[0 : top[2]])) if top[0] else None,
        )

    @staticmethod
    def give_back(child: Child) -> tuple[int, int]:
        """An abandoned child's held context (``abandon(hold_context=True)``):
        the blocks others freed for its slot freed now and its memory given
        back (contexts.c cg_child_give_back), then the context back to the
        pool. (Python object blocks, native blocks); -1: not that kind here
        (no guard, glibc, a quarantined slot)."""
        ffi, lib = _lib()
        counts = ffi.new("long[2]")
        lib.cg_child_give_back(child._block, counts)
        return counts[0], counts[1]

    # -- the herald (herald.c): CRASHED events published without Python ------

    def start_herald(self, publish: int, write_death: int, publisher: int) -> None:
        """From now on the core publishes an armed child's CRASHED event
        itself, at its death. ``publish``, ``write_death``: the addresses of
        rclglue's cgr_event_publish and cgr_event_write_death; ``publisher``:
        an rcl_publisher_t's, which must outlive stop_herald() (close() calls
        it). ``EventPublisher.publish_from_c()`` gives all three."""
        ffi, lib = _lib()
        rc = lib.cg_herald_start(
            ffi.cast("void *", publish), ffi.cast("void *", write_death), ffi.cast("void *", publisher)
        )
        if rc < 0:
            raise OSError(-rc, f"cannot start the herald: {os.strerror(-rc)}")

    def stop_herald(self, timeout: float = 2.0) -> bool:
        """Publish what was claimed, claim no more: every death after it is
        Python's to report. False if the herald is still inside a publish
        after ``timeout`` (then its publisher must never be destroyed); True
        otherwise, and when it was not running."""
        _, lib = _lib()
        return lib.cg_herald_stop(int(timeout * 1000)) != -errno.ETIMEDOUT

    def herald_failures(self) -> int:
        """CRASHED events the herald failed to publish since the core was
        loaded; each is also said on stderr."""
        _, lib = _lib()
        return int(lib.cg_herald_failures())

    def arm_crashed(self, child: Child, event: ComponentEvent) -> bool:
        """Have the herald publish ``event``, the child's CRASHED with every
        field known now, if it dies; the death's own fields (exit signal or
        code, allocator_quarantined, error_message) come from the monitor.
        False if it is dead already."""
        from cloneguard.container import events  # ROS's: imported where needed

        ffi, lib = _lib()
        # The room the death's words get (rclglue writes them in, allocating nothing).
        event.error_message = " " * (lib.CG_DEATH_TEXT - 1)
        c_event = events.in_c(event)
        with self._lock:
            rc = -errno.ESRCH
            if not self._entry(child).dead:
                rc = lib.cg_herald_arm(
                    child._block,
                    ffi.cast("void *", c_event.pointer),
                    ffi.cast("void *", c_event.destroy_address),
                    event.full_node_name.encode(),
                    event.pid,
                )
        if rc < 0:
            c_event.destroy()  # still ours
            if rc == -errno.ESRCH:
                return False
            raise OSError(-rc, f"cannot arm the CRASHED event: {os.strerror(-rc)}")
        return True

    def disarm_crashed(self, child: Child) -> bool:
        """Take the child's CRASHED event back from the herald: True if its
        death, if any, is the caller's to report; False if the herald has
        announced it (the child is dead)."""
        _, lib = _lib()
        with self._lock:
            self._entry(child)
            return bool(lib.cg_herald_disarm(child._block))

    def crashed_claimed(self, child: Child) -> bool:
        """The herald has announced the child's death (it may not be reported
        to on_event yet)."""
        _, lib = _lib()
        with self._lock:
            entry = self._entries.get(child.serial)
            return entry is not None and entry.child is child and bool(lib.cg_herald_claimed(child._block))

    allocator = staticmethod(allocator)

    def set_memory_limit(self, child: Child, limit_bytes: int) -> bool:
        """The child's memory budget from now on (0: none): a node process
        whose memory in use (``memory``) would go over it ends itself before
        the allocation, its death saying so. False without the guard."""
        _, lib = _lib()
        with self._lock:
            self._entry(child)
            return lib.cg_child_set_memory_limit(child._block, limit_bytes) == 0

    def memory(self, child: Child) -> tuple[int, int] | None:
        """(bytes in use, budget in bytes, 0: none) of the child's process,
        as the allocator guard counts them (allocguard.c says what is
        counted); None without the guard."""
        ffi, lib = _lib()
        out = ffi.new("struct cga_slot_memory *")
        with self._lock:
            self._entry(child)
            if lib.cg_child_memory(child._block, out) != 0:
                return None
        return int(out.in_use), int(out.limit)

    def slot_stats(self, slot: int) -> dict | None:
        """What allocator-guard slot ``slot`` (a Death's ``alloc_slot``)
        holds: state ("idle", "bound", "quarantined"), pid, jemalloc arena,
        glibc arenas, blocks handed to it by others, and of those the ones
        not taken back yet (``pending_blocks``/``pending_bytes``: for a
        quarantined slot, what leaked) and the small ones taken back but
        held until its next drain, so that a second free of one is caught
        (``held_blocks``/``held_bytes``); both counted only while no process
        is bound to it; and its Python pools (``python``). None without the
        guard."""
        ffi, lib = _lib()
        out = ffi.new("struct cga_slot_stats *")
        if lib.cg_alloc_slot_stats(slot, out) < 0:
            return None
        states = {
            lib.CGA_UNUSED: "unused",
            lib.CGA_IDLE: "idle",
            lib.CGA_BOUND: "bound",
            lib.CGA_QUARANTINED: "quarantined",
        }
        return {
            "state": states.get(out.state, str(out.state)),
            "pid": out.pid,
            "arena": out.arena,
            "glibc_arenas": out.glibc_arenas,
            "handed_blocks": out.handed_blocks,
            "pending_blocks": out.pending_blocks,
            "pending_bytes": out.pending_bytes,
            "held_blocks": out.held_blocks,
            "held_bytes": out.held_bytes,
            "main_arena_allocs": out.main_arena_allocs,
            "python": self._py_slot_stats(slot),
        }

    @staticmethod
    def _py_slot_stats(slot: int) -> dict | None:
        """CPython's object pools of the slot (pyalloc.c): their generation
        (one more each time they were abandoned), pools taken, blocks others
        handed to it, frees into abandoned pools left undone, and deaths
        inside them. None without the pools."""
        ffi, lib = _lib()
        py = ffi.new("struct cga_py_stats *")
        if lib.cg_py_slot_stats(slot, py) < 0:
            return None
        return {k: getattr(py, k) for k in ("generation", "pools", "handed", "dropped", "abandoned")}

    def _no_free_slot(self) -> str | None:
        """Why a spawn found no allocator-guard slot, if that is why: every
        slot is bound to a live node or quarantined (its node died inside
        malloc; its arena is never used again)."""
        counts: dict[str, int] = {}
        slot = 1  # slot 0 is the container's
        while (stats := self.slot_stats(slot)) is not None:
            counts[stats["state"]] = counts.get(stats["state"], 0) + 1
            slot += 1
        if not counts or counts.get("idle", 0) or counts.get("unused", 0):
            return None
        return (
            f"no allocator slot is free: {counts.get('quarantined', 0)} of {slot - 1} are quarantined "
            f"(their nodes died inside malloc) and {counts.get('bound', 0)} in use; "
            "a restart of the container frees the quarantined ones"
        )

    def flush_crash_reports(self, timeout: float | None = None) -> bool:
        """Wait until the stacks of every crash reported so far are written
        (crash_reports.py); False on timeout."""
        return self._crash_stacks.flush(timeout)

    def children(self) -> list[Child]:
        """Children spawned and not yet released."""
        with self._lock:
            return [e.child for e in self._entries.values() if e.child]

    # -- shutdown ---------------------------------------------------------
    def close(self, *, kill: bool = True, timeout: float = 10.0) -> None:
        """Stop the monitor.  With kill=True, SIGKILL, reap and release every
        child first; with kill=False refuse (RuntimeError) while any lives.
        """
        if threading.current_thread() is self._listener:
            raise RuntimeError("close() cannot be called from on_event")
        self.stop_herald()  # the deaths below are not crashes to announce
        with self._lock:
            if self._stopped:
                return
            self._closed = True  # no new spawn from here on
            self._changed.wait_for(lambda: self._spawning == 0)
            live = [e for e in self._entries.values() if not e.dead]
            if live and not kill:
                self._closed = False
                raise RuntimeError(f"{len(live)} children still alive")
        for e in live:
            self.kill(e.child, signal.SIGKILL)
        for e in live:
            if not self._wait_entry(e.is_dead, timeout):
                raise TimeoutError(f"child {e.child.pid} not reaped after SIGKILL")
        # A death reported before close() may still be in on_event, which
        # may release that child itself: let it finish first, so that no
        # child is released twice (or under its handler's feet).
        with self._lock:
            left = list(self._entries.values())
        for e in left:
            if not self._wait_entry(e.death_was_reported, timeout):
                print(
                    f"cloneguard: on_event for child {e.child.pid} still running after "
                    f"{timeout:g} s; releasing it anyway",
                    file=sys.stderr,
                )
        for e in left:
            try:
                self.release(e.child)
            except ValueError:  # its on_event released it
                pass
        self._shutdown_monitor()
        self._stopped = True
        if self._collector is not None:  # no child runs Python any more
            self._collector.close()
        self._listener.join()  # it closes the event fd
        if not self._crash_stacks.close(timeout):
            print(
                f"cloneguard: a crashed child's stacks were not written within {timeout:g} s "
                "(the dynamic loader's lock is taken?)",
                file=sys.stderr,
            )

    def __enter__(self) -> CloneCore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals --------------------------------------------------------
    def _shutdown_monitor(self) -> None:
        _, lib = _lib()
        rc = lib.cg_stop()
        if rc < 0:
            raise OSError(-rc, f"cannot stop the monitor: {os.strerror(-rc)}")
        self._unwatch_memory()
        with CloneCore._instance_lock:
            CloneCore._open = None

    @staticmethod
    def _watch_memory(watch: tuple[MemoryLimit, int] | None) -> tuple[int, ...]:
        if watch is None:
            return ()
        limit, margin = watch
        usage, stat = memory_watch.open_files(limit)
        _, lib = _lib()
        rc = lib.cg_memwatch_set(usage, stat, limit.stat_key.encode(), int(limit.meminfo), limit.limit, margin)
        if rc < 0:
            for fd in (usage, stat):
                if fd >= 0:
                    os.close(fd)
            raise ValueError(f"memory watch: a margin of {margin} bytes under a limit of {limit.limit}")
        return tuple(fd for fd in (usage, stat) if fd >= 0)

    def _unwatch_memory(self) -> None:
        _, lib = _lib()
        lib.cg_memwatch_set(-1, -1, b"", 0, 0, 0)
        for fd in self._watch_fds:
            os.close(fd)
        self._watch_fds = ()

    @staticmethod
    def monitor_realtime() -> str | None:
        """None if the monitor thread runs real-time (SCHED_FIFO, monitor.c:
        no node's use of the CPU delays it); else why not."""
        _, lib = _lib()
        err = lib.cg_monitor_realtime()
        return None if err == 0 else os.strerror(err)

    def set_oom_score_adj(self, child: Child, adj: int) -> None:
        """How the memory watch scores the child (-1000 to 1000, as the
        kernel's oom_score_adj: -1000 never ends it)."""
        _, lib = _lib()
        with self._lock:
            self._entry(child)
            if lib.cg_child_set_oom_score_adj(child._block, adj) < 0:
                raise ValueError(f"an oom_score_adj is from -1000 to 1000, not {adj}")

    def _wait_entry(self, flag: Callable[[], bool], timeout: float | None) -> bool:
        with self._lock:
            return self._changed.wait_for(flag, timeout)

    def _entry(self, child: Child) -> _Entry:
        """Look a child up; caller holds self._lock."""
        entry = self._entries.get(child.serial)
        if entry is None or entry.child is not child:
            raise ValueError(f"{child} is not an unreleased child of this CloneCore")
        return entry

    def _listen(self) -> None:
        try:
            pending = b""
            while True:
                data = os.read(self._event_fd, RECORD_SIZE * 64)  # GIL released
                if not data:
                    return
                pending += data
                while len(pending) >= RECORD_SIZE:
                    rec, pending = pending[:RECORD_SIZE], pending[RECORD_SIZE:]
                    kind, event = decode(rec)
                    if kind == KIND_CLOSED:
                        return
                    assert event is not None, f"a record of a kind the monitor never sends: {kind}"
                    self._dispatch(kind, event)
        finally:
            os.close(self._event_fd)

    def _dispatch(self, kind: int, event: CoreEvent) -> None:
        if kind == KIND_MUTEX:  # of a child that may be released already
            self._call_on_event(event)
            return
        with self._lock:
            entry = self._entries.get(event.serial)
        if entry is None:
            return
        with self._lock:  # never report a child before spawn() returns
            self._changed.wait_for(lambda: entry.spawned)
        stacks = None
        if isinstance(event, Death):
            if self._pylocks is not None:
                self._pylocks.node_died(event.pid)
            # Before anything can release the child's control block.
            ffi, lib = _lib()
            block = entry.child._block
            stacks = self._crash_stacks.take(block)
            event = replace(event, text=ffi.string(block.death_text).decode(errors="replace"))
            if block.crash_si_code == lib.SEGV_PKUERR and block.crash_pkey:
                event = replace(event, pkey_fault=self._pkey_fault(block))
            if block.gil_code != ffi.NULL:
                buf = ffi.new("char[]", 512)
                lib.cg_frame_text(block.gil_code, block.gil_lasti, buf, 512)
                event = replace(event, gil_frame=ffi.string(buf).decode(errors="replace"))
            if block.core_dump == lib.CG_CORE_DONE:
                event = replace(event, core_file=ffi.string(block.core_path).decode(errors="replace"))
            elif block.core_dump == lib.CG_CORE_FAILED:
                event = replace(event, core_missing=ffi.string(block.core_why).decode(errors="replace"))
            with self._lock:
                entry.death = event
                entry.target = None  # reaped: nothing runs it any more
                entry.dead = True
                self._changed.notify_all()
        try:
            self._call_on_event(event)
        finally:
            if stacks is not None:  # after on_event reported the death (CRASHED)
                self._crash_stacks.submit(event.pid, stacks)
            if kind == KIND_DEATH:
                with self._lock:
                    entry.death_reported = True
                    self._changed.notify_all()

    def _pkey_fault(self, block: Any) -> PkeyFault:
        ffi, lib = _lib()
        addr = int(ffi.cast("uintptr_t", block.crash_addr))
        slot = lib.cg_alloc_slot_of(block.crash_addr)
        with self._lock:  # the live child in that slot: the victim
            victims = [
                e.child.pid
                for e in self._entries.values()
                if not e.dead
                and e.child is not None  # still being spawned
                and e.child._block is not None
                and lib.cg_child_slot(e.child._block) == slot
            ]
        return PkeyFault(addr, block.crash_pkey, slot, victims[0] if victims and slot > 0 else 0)

    def _call_on_event(self, event: CoreEvent) -> None:
        try:
            if self._on_event is not None:
                self._on_event(event)
        except Exception:
            print("cloneguard: on_event raised:", file=sys.stderr)
            traceback.print_exc()


@atexit.register
def _close_at_exit() -> None:
    """Kill and reap children before the interpreter they run in goes away."""
    core = CloneCore._open
    if core is not None:
        try:
            core.close()
        except Exception:
            traceback.print_exc()
