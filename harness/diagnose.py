"""Why is it stuck? Native (and Python) stacks of a hung container and of its
live node processes, what each thread waits on, and who holds it.

gdb (batch mode) attaches to the container and to every node process that
is still alive (each is a thread group of its own, in the same address
space) and prints every thread's backtrace, and its Python stack where
CPython's gdb extension is at hand. Each thread's innermost waiting frame
says what it waits for:

* ``pthread_mutex_lock``/``__pthread_mutex_cond_lock (mutex=0x..)``: a pthread
  mutex (Fast DDS's and rclcpp's std::mutex, jemalloc's locks, ...); its
  ``__owner`` field names the owning tid, read with a second gdb call;
* ``__lll_lock_wait_private`` under malloc/free/realloc: a glibc malloc arena
  lock. It records no owner: when no live thread is inside that arena, it is
  held by a task that is gone, and the dead node processes are named;
* ``take_gil``: the interpreter lock; ``_PyRuntime.ceval.gil.last_holder``
  names the thread state that holds it, and so its native thread id.

A thread that waits on no lock is idle (in epoll/poll/recv/read, a condition
variable, a sleep), waits on a Python lock (a semaphore, no owner), or runs
(a spin: named by its innermost function). When no thread waits on a lock,
the summary says that, and what the node processes' main threads do.

An owner tid that belongs to a node's process that has died (the caller
passes what it knows: pid -> node name, and which pids are dead) is named.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from . import procfs

if TYPE_CHECKING:
    from .client import ContainerClient
    from .process import ContainerProcess

GDB_TIMEOUT_S = 90
# How the container's own log lines about a lock it left as it was begin
# (its container/repairs.py NOT_REPAIRED): a diagnosis quotes them first,
# naming the lock as the container did.
CONTAINER_NOT_REPAIRED = "lock not repaired: "
# CPU use of every thread is sampled over this window before the stacks are
# taken; at SPIN_PERCENT or more of a CPU a thread of a hung container is
# called spinning.
CPU_WINDOW_S = 0.5
# A stack shows a moment, and a thread caught waiting on a lock may have it
# a moment later (a busy lock; the GIL passed from thread to thread): each
# such waiter's system call is read again RECHECKS times over RECHECK_S
# once the stacks are taken (_passing).
RECHECKS = 10
RECHECK_S = 0.2
SPIN_PERCENT = 50
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
UNNAMED_CHILD = "a child process no event named"
# CPython's gdb extension (py-bt), where the interpreter installed it.
PY_GDB = Path(sys.base_prefix) / "bin" / f"python{sys.version_info[0]}.{sys.version_info[1]}-gdb.py"

_THREAD = re.compile(r'^Thread \d+ \(Thread 0x[0-9a-f]+ \(LWP (\d+)\)(?: "([^"]*)")?\)')
_FRAME = re.compile(r"^#(\d+)\s+(?:0x[0-9a-f]+ in )?(\S.*?) \((.*)")  # a C++ name may hold spaces
_PY_FILE = re.compile(r'^\s*File "([^"]+)", line (\S+), in (\S+)')
_MUTEX_ARG = re.compile(r"mutex=(?:mutex@entry=)?(0x[0-9a-f]+)")
_FUTEX_ARG = re.compile(r"futex=(?:futex@entry=)?(0x[0-9a-f]+)(?: <([^>]+)>)?")
_AV_ARG = re.compile(r"\bav=(?:av@entry=)?(0x[0-9a-f]+)")
_MALLOC_FUNCS = ("malloc", "free", "realloc", "calloc", "_int_free", "arena_get", "tcache")
_MUTEX_FUNCS = ("pthread_mutex_lock", "pthread_mutex_timedlock", "pthread_mutex_clocklock", "__pthread_mutex_cond_lock")
_LIBC_LOCK_FRAMES = ("___pthread", "__pthread", "pthread_mutex", "lll_", "__GI_", "__lll_")
# Locks every node process of a container shares, by the function that takes
# them: per-node isolation cannot keep a dead node's hold on them from the rest.
SHARED_LOCKS = {
    "TopicPayloadPool": "Fast DDS's payload pool of one topic, shared by every participant in the process "
    "(TopicPayloadPoolRegistry)",
    "take_gil": "the GIL's own mutex (CPython's gil->mutex), taken by every thread that takes the GIL",
    "drop_gil": "the GIL's own mutex (CPython's gil->mutex), taken by every thread that drops the GIL",
}
# Loops in other projects' code that wait by spinning, by a frame they run in.
KNOWN_BUSY_WAITS = {
    "DomainParticipant::set_listener": "Fast DDS 2.14 busy-waits there, with the lock its participant-listener "
    "callbacks need, for those callbacks to end: eProsima/Fast-DDS#6513",
}
_IDLE_FUNCS = (
    "epoll_wait",
    "epoll_pwait",
    "poll",
    "ppoll",
    "select",
    "pselect",
    "recvfrom",
    "recvmsg",
    "recv",
    "read",
    "__libc_read",
    "accept",
    "nanosleep",
    "clock_nanosleep",
    "sigwait",
    "sigtimedwait",
    "pause",
    "waitid",
    "wait4",
    "futex_wait",
)


@dataclass
class ThreadStack:
    tid: int
    name: str
    pid: int = 0  # its process (thread group)
    frames: list[str] = field(default_factory=list)  # function names, innermost first
    raw: list[str] = field(default_factory=list)
    python: list[str] = field(default_factory=list)  # "func (file:line)", innermost first


@dataclass(frozen=True)
class BlockedOn:
    tid: int
    kind: str  # "pthread mutex", "jemalloc lock", "malloc arena lock", "GIL"
    address: str  # the lock's address, "" when not known
    owner_tid: int | None
    owner_node: str | None
    owner_dead: bool
    pid: int = 0  # the waiting thread's process
    where: str = ""  # the waiter: node name / "container"
    note: str = ""  # the next best fact when the owner is not recorded
    taker: str = ""  # the function that wants the lock (a mutex's caller)

    def describe(self) -> str:
        owner = "no owner recorded"
        if self.owner_tid is not None:
            owner = f"owned by tid {self.owner_tid}"
            if self.owner_node == UNNAMED_CHILD:
                owner += f" ({self.owner_node})"
            elif self.owner_node:
                owner += f" ({'dead ' if self.owner_dead else ''}node {self.owner_node})"
            elif self.owner_dead:
                owner += " (a dead process)"
            elif self.note:
                owner += f" ({self.note})"
        elif self.note:
            owner = self.note
        at = f" at {self.address}" if self.address else ""
        if self.taker:
            known = next((what for key, what in SHARED_LOCKS.items() if key in self.taker), "")
            at += f" (taken in {self.taker}{': ' + known if known else ''})"
        who = f"tid {self.tid}" + (f" ({self.where})" if self.where else "")
        return f"{who} waits on the {self.kind}{at}, {owner}"


@dataclass
class ThreadState:
    tid: int
    pid: int
    state: str  # "blocked", "idle", "python lock", "running"
    what: str  # the function (and Python frame) it is in
    cpu_percent: int = 0  # CPU it used in the sampling window before the stacks were taken


@dataclass
class Diagnosis:
    pid: int
    stacks_text: str
    threads: list[ThreadStack]
    blocked: list[BlockedOn]
    states: list[ThreadState] = field(default_factory=list)
    names: dict[int, str] = field(default_factory=dict)  # pid -> "container" / node name
    container_said: list[str] = field(default_factory=list)  # its "lock not repaired" lines

    def summary(self) -> str:
        said = [f"the container said: {line}" for line in self.container_said]
        return "; ".join([*said, self._threads_summary()])

    def _threads_summary(self) -> str:
        spinning = [
            f"{self.names.get(s.pid, '?')} tid {s.tid} spinning ({s.cpu_percent}% of a CPU "
            f"while nothing progressed): {s.what}"
            for s in self.states
            if s.cpu_percent >= SPIN_PERCENT
        ]
        if self.blocked:
            return "; ".join([b.describe() for b in self.blocked] + spinning)
        facts = list(spinning)
        for pid, name in self.names.items():
            main = next((s for s in self.states if s.tid == pid), None)
            busy = [s for s in self.states if s.pid == pid and s.state != "idle" and s.cpu_percent < SPIN_PERCENT]
            if main is not None and (main.state != "idle" or pid != self.pid):
                facts.append(f"{name} (pid {pid}) main thread {main.state}: {main.what}")
            facts.extend(f"{name} tid {s.tid} {s.state}: {s.what}" for s in busy if s is not main)
        if not facts:
            facts.append("every thread is idle (waiting for work that never comes)")
        return "no thread waits on a lock; " + "; ".join(facts)


def gdb_available() -> bool:
    return shutil.which("gdb") is not None


def _gdb(pid: int, commands: list[str]) -> str:
    argv = ["gdb", "-p", str(pid), "-batch", "-nx", "-ex", "set pagination off"]
    for c in commands:
        argv += ["-ex", c]
    try:
        out = subprocess.run(argv, capture_output=True, text=True, timeout=GDB_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return ""
    return out.stdout


def parse_threads(text: str, pid: int = 0) -> list[ThreadStack]:
    """Native backtraces (``thread apply all bt``), then, if present, Python
    stacks (``thread apply all py-bt``) matched to their threads by tid."""
    threads: dict[int, ThreadStack] = {}
    order: list[ThreadStack] = []
    current = None
    for line in text.splitlines():
        m = _THREAD.match(line)
        if m:
            tid = int(m.group(1))
            current = threads.get(tid)
            if current is None:
                current = threads[tid] = ThreadStack(tid, m.group(2) or "", pid)
                order.append(current)
            continue
        if current is None:
            continue
        f = _FRAME.match(line)
        if f:
            current.frames.append(f.group(2))
            current.raw.append(line)
            continue
        p = _PY_FILE.match(line)
        if p:
            current.python.append(f"{p.group(3)} ({Path(p.group(1)).name}:{p.group(2)})")
    return order


def _lock_wait(t: ThreadStack) -> tuple[str, str, str] | None:
    """(kind, address, symbol) of the lock the thread waits on, or None;
    for a mutex, the symbol is the function that takes it."""
    for i, (fn, raw) in enumerate(zip(t.frames, t.raw, strict=True)):
        if fn == "take_gil":
            return "GIL", "", ""
        if any(name in fn for name in _MUTEX_FUNCS):
            m = _MUTEX_ARG.search(raw)
            outer = " ".join(t.raw[i + 1 : i + 3])
            kind = "jemalloc lock" if "libjemalloc" in outer else "pthread mutex"
            taker = (
                ""
                if kind == "jemalloc lock"
                else next((f for f in t.frames[i + 1 :] if not f.startswith(_LIBC_LOCK_FRAMES) and f != "??"), "")
            )
            return kind, m.group(1) if m else "", taker.split("(")[0]
        if fn.endswith("lll_lock_wait_private") or fn.endswith("lll_lock_wait"):
            callers = t.frames[i + 1 : i + 4]
            if any(any(k in o for k in _MALLOC_FUNCS) for o in callers):
                m = _FUTEX_ARG.search(raw)
                return "malloc arena lock", m.group(1) if m else "", (m.group(2) or "") if m else ""
    return None


def _where(t: ThreadStack) -> str:
    skip = (
        "futex",
        "__GI_",
        "syscall",
        "do_futex_wait",
        "__new_sem_wait",
        "___sem_",
        "__pthread_cond",
        "___pthread_cond",
        "__lll_",
        "lll_",
    )
    native = next((f for f in t.frames if not f.startswith(skip) and f != "??"), t.frames[0] if t.frames else "?")
    known = next(((f.split("(")[0], why) for f in t.frames for key, why in KNOWN_BUSY_WAITS.items() if key in f), None)
    if known and not native.startswith(known[0]):
        native += f" in {known[0]} ({known[1]})"
    return native + (f" [Python: {t.python[0]}]" if t.python else "")


def _state(t: ThreadStack) -> tuple[str, str]:
    top = t.frames[:10]
    if any(f.startswith("PyThread_acquire_lock") for f in top):
        return "python lock", _where(t)
    waiting = top[:1] and ("futex" in top[0] or any(top[0].endswith(i) for i in _IDLE_FUNCS))
    if waiting or any("pthread_cond" in f for f in top):
        return "idle", _where(t)
    return "running", _where(t)


_GIL = "_PyRuntime.ceval.gil"
#: What gdb reads in the container for a wait on the GIL: its last holder's
#: native thread id, and where CPython's GIL state (its mutexes and
#: condition variables, every futex word a GIL wait sleeps on) lies.
_GIL_READS = {
    ("GIL", ""): f"((PyThreadState *){_GIL}.last_holder._value)->native_thread_id",
    ("GIL start", ""): f"(long)&{_GIL}",
    ("GIL size", ""): f"(long)sizeof({_GIL})",
}
_GIL_FRAMES = ("take_gil", "drop_gil")


def _read_ints(pid: int, expressions: list[str]) -> list[int | None]:
    """Evaluate integer expressions in ``pid`` with one gdb call."""
    if not expressions:
        return []
    text = _gdb(pid, [f"print {x}" for x in expressions])
    values: dict[int, int] = {}
    for m in re.finditer(r"^\$(\d+) = (-?\d+)", text, re.M):
        values[int(m.group(1))] = int(m.group(2))
    return [values.get(i + 1) for i in range(len(expressions))]


def _inside_arena(threads: list[ThreadStack], arena: str) -> list[int]:
    """Live threads whose stacks are inside glibc malloc on ``arena`` (and
    not just waiting for its lock)."""
    out = []
    for t in threads:
        if _lock_wait(t) is not None:
            continue
        if any(arena == m.group(1) for r in t.raw if (m := _AV_ARG.search(r))):
            out.append(t.tid)
    return out


def not_repaired_lines(log: str) -> list[str]:
    """The container's own reports, in its log, of locks it left as they were
    (the part after the mark; each once)."""
    out = []
    for line in log.splitlines():
        _, mark, rest = line.partition(CONTAINER_NOT_REPAIRED)
        if mark and rest not in out:
            out.append(rest)
    return out


def diagnose(
    pid: int,
    *,
    nodes_by_pid: dict[int, str] | None = None,
    dead_pids: set[int] | frozenset[int] = frozenset(),
    log: str = "",
) -> Diagnosis:
    """Attach to the container ``pid``, each live node process and any other
    live child of it with gdb and say what their threads are blocked on;
    with the container's ``log``, quote first what it said of locks it could
    not repair."""
    nodes_by_pid = nodes_by_pid or {}
    names = {pid: "container"}
    names.update({p: n for p, n in sorted(nodes_by_pid.items()) if p not in dead_pids and p != pid and procfs.alive(p)})
    # Its other children too: a process no event named (a per-node
    # container's warm spare, or a node whose LOADED was not seen yet) can
    # be the one that holds what the rest wait for.
    names.update(
        {p: UNNAMED_CHILD for p in procfs.children_of(pid) if p not in names and p not in dead_pids and procfs.alive(p)}
    )
    # A stack shows a moment; CPU time over a window says who is spinning
    # (a livelock, a busy wait on something that never comes) and who waits.
    before = {p: procfs.thread_cpu_ticks(p) for p in names}
    time.sleep(CPU_WINDOW_S)
    after = {p: procfs.thread_cpu_ticks(p) for p in names}
    cpu = {
        tid: round(100 * (ticks - before[p].get(tid, ticks)) / (CLOCK_TICKS * CPU_WINDOW_S))
        for p in names
        for tid, ticks in after[p].items()
    }
    commands = ["thread apply all bt 40"]
    if PY_GDB.is_file():
        commands = [f"source {PY_GDB}", *commands, "thread apply all py-bt"]
    texts, threads = [], []
    for p, name in names.items():
        text = _gdb(p, commands)
        texts.append(f"===== {name} (pid {p}) =====\n{text}")
        threads.extend(parse_threads(text, p))
    waits = [(t, _lock_wait(t)) for t in threads]
    owners = _owners(pid, waits)
    start, size = owners.get(("GIL start", "")), owners.get(("GIL size", ""))
    passing = _passing(waits, (start, start + size) if start and size else None)
    waits = [(t, None if t.tid in passing else what) for t, what in waits]
    blocked, states = [], []
    for t, what in waits:
        if what is None:
            state, where = _state(t)
            states.append(ThreadState(t.tid, t.pid, state, where, cpu.get(t.tid, 0)))
            continue
        states.append(ThreadState(t.tid, t.pid, "blocked", _where(t), cpu.get(t.tid, 0)))
        kind, addr, symbol = what
        owner, note = owners.get((kind, addr)), ""
        if kind == "malloc arena lock":
            arena = symbol or addr
            inside = _inside_arena(threads, addr) if addr else []
            if inside:
                note = f"{arena}: glibc records no owner; live threads inside it: {inside}"
            else:
                dead = sorted(f"{nodes_by_pid.get(d, '?')} (pid {d})" for d in dead_pids)
                note = (
                    f"{arena}: glibc records no owner and no live thread is inside it, so a "
                    f"task that is gone holds it" + (f"; dead node processes: {', '.join(dead)}" if dead else "")
                )
        owner = owner or None
        if owner and not note and owner not in {s.tid for s in threads}:
            # Owned by a task in no process we looked into: say what it is.
            facts = procfs.task_facts(owner)
            note = f"tid {owner}: {facts}" if facts else ""
        # The owner's process, where it is one we looked into: a node's
        # thread other than its first, or a child no event named.
        owner_pid = next((s.pid for s in threads if s.tid == owner), None) if owner else None
        owner_name = nodes_by_pid.get(owner) if owner else None
        if owner_name is None and owner_pid not in (None, pid):
            owner_name = names.get(owner_pid)
        blocked.append(
            BlockedOn(
                tid=t.tid,
                kind=kind,
                address=addr,
                owner_tid=owner,
                owner_node=owner_name,
                owner_dead=owner is not None and owner > 0 and (owner in dead_pids or not procfs.alive(owner)),
                pid=t.pid,
                where=names.get(t.pid, ""),
                note=note,
                taker=symbol if kind != "malloc arena lock" else "",
            )
        )
    return Diagnosis(pid, "\n".join(texts), threads, blocked, states, names, not_repaired_lines(log))


def of_container(proc: ContainerProcess, client: ContainerClient) -> Diagnosis | None:
    """The diagnosis of a hung container (a ContainerProcess) whose
    ContainerClient saw its events, naming its nodes from them; None
    where gdb is missing."""
    if not gdb_available() or not procfs.alive(proc.pid):
        return None
    return diagnose(proc.pid, nodes_by_pid=client.nodes_by_pid(), dead_pids=client.dead_pids(), log=proc.log_text())


def _owners(
    pid: int, waits: Iterable[tuple[ThreadStack, tuple[str, str, str] | None]]
) -> dict[tuple[str, str], int | None]:
    """The owner tid of every lock waited on that records one: a mutex's
    ``__owner`` (read in the waiter's process: one gdb call per process),
    the GIL's last holder (one interpreter: read once, in the container)."""
    wanted: dict[int, list[tuple[str, str]]] = {}
    for t, what in waits:
        if what is None:
            continue
        kind, addr, _ = what
        if _on_the_gil(t):  # where the GIL lies too: its waits are rechecked against it
            wanted.setdefault(pid, []).extend(_GIL_READS)
        if kind != "GIL" and addr and kind != "malloc arena lock":
            wanted.setdefault(t.pid, []).append((kind, addr))
    owners: dict = {}
    for p, keys in wanted.items():
        keys = list(dict.fromkeys(keys))
        exprs = [_GIL_READS.get(key) or f"((int *){key[1]})[2]" for key in keys]  # __owner
        owners.update(zip(keys, _read_ints(p, exprs), strict=True))
    return owners


def _on_the_gil(t: ThreadStack) -> bool:
    """Its lock wait is part of taking or dropping the GIL."""
    return any(f in _GIL_FRAMES for f in t.frames)


def _passing(waits: Sequence[tuple[ThreadStack, tuple[str, str, str] | None]], gil: tuple[int, int] | None) -> set[int]:
    """The tids whose lock wait the stacks caught was a passing one: read
    again after the stacks (its system call, RECHECKS times over
    RECHECK_S), the thread sleeps in another call, or on another futex
    word than the lock's (a mutex's is at its start; a GIL wait's anywhere
    in CPython's GIL state, ``gil``: (start, end), any futex word when
    not known). A thread seen only running gives no sign either way."""
    words: dict[int, tuple[int, int] | None] = {}
    for t, what in waits:
        if what is not None:
            addr = int(what[1], 16) if what[1] else None
            words[t.tid] = gil if _on_the_gil(t) else (addr, addr + 4) if addr is not None else None
    moved: set[int] = set()
    if not words:  # nobody waits on a lock: nothing to read again, no time to spend
        return moved
    for i in range(RECHECKS):
        if i:
            time.sleep(RECHECK_S / (RECHECKS - 1))
        for tid, span in words.items():
            now = procfs.syscall_now(tid) if tid not in moved else None
            if now is None:
                continue
            number, word = now
            if number != procfs.SYS_FUTEX or (span is not None and not span[0] <= word < span[1]):
                moved.add(tid)
    return moved
