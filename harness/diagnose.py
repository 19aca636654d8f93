"""Why is it stuck? Native stacks of a hung container, the lock each thread
waits on, and who owns it.

gdb (batch mode) attaches to the container and prints every thread's
backtrace. Each thread's innermost waiting frame says what it waits for:

* ``pthread_mutex_lock (mutex=0x..)``: a pthread mutex; its ``__owner`` field
  names the owning tid, read with a second gdb call;
* ``__lll_lock_wait_private`` under malloc/free/realloc: a glibc malloc
  arena lock, which records no owner;
* ``take_gil``: the interpreter lock; ``_PyRuntime.ceval.gil.last_holder``
  names the thread state that holds it, and so its native thread id.

An owner tid that belongs to a node's process that has died (the caller
passes what it knows: pid -> node name, and which pids are dead) is named.
"""
from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass, field

from . import procfs

GDB_TIMEOUT_S = 90

_THREAD = re.compile(r'^Thread \d+ \(Thread 0x[0-9a-f]+ \(LWP (\d+)\)(?: "([^"]*)")?\)')
_FRAME = re.compile(r"^#(\d+)\s+(?:0x[0-9a-f]+ in )?(\S+) \((.*)")
_MUTEX_ARG = re.compile(r"mutex=(?:mutex@entry=)?(0x[0-9a-f]+)")
_FUTEX_ARG = re.compile(r"futex=(?:futex@entry=)?(0x[0-9a-f]+)")
_MALLOC_FUNCS = ("malloc", "free", "realloc", "calloc", "_int_free", "arena_get", "tcache")


@dataclass
class ThreadStack:
    tid: int
    name: str
    frames: list[str] = field(default_factory=list)   # function names, innermost first
    raw: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class BlockedOn:
    tid: int
    kind: str             # "pthread mutex", "malloc arena lock", "GIL"
    address: str          # the lock's address, "" when not known
    owner_tid: int | None
    owner_node: str | None
    owner_dead: bool

    def describe(self) -> str:
        owner = ("owner unknown (glibc arena locks record none)" if self.kind == "malloc arena lock"
                 else "no owner recorded")
        if self.owner_tid is not None:
            owner = f"owned by tid {self.owner_tid}"
            if self.owner_node:
                owner += f" ({'dead ' if self.owner_dead else ''}node {self.owner_node})"
            elif self.owner_dead:
                owner += " (a dead process)"
        where = f" at {self.address}" if self.address else ""
        return f"tid {self.tid} waits on the {self.kind}{where}, {owner}"


@dataclass
class Diagnosis:
    pid: int
    stacks_text: str
    threads: list[ThreadStack]
    blocked: list[BlockedOn]

    def summary(self) -> str:
        if not self.blocked:
            return f"pid {self.pid}: no thread is waiting on a lock gdb could name"
        return "; ".join(b.describe() for b in self.blocked)


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


def parse_threads(text: str) -> list[ThreadStack]:
    threads, current = [], None
    for line in text.splitlines():
        m = _THREAD.match(line)
        if m:
            current = ThreadStack(int(m.group(1)), m.group(2) or "")
            threads.append(current)
            continue
        f = _FRAME.match(line)
        if f and current is not None:
            current.frames.append(f.group(2))
            current.raw.append(line)
    return threads


def _classify(t: ThreadStack) -> tuple[str, str] | None:
    """(kind, address) of what the thread waits on, or None."""
    for i, (fn, raw) in enumerate(zip(t.frames, t.raw)):
        if fn == "take_gil":
            return "GIL", ""
        if "pthread_mutex_lock" in fn or "pthread_mutex_timedlock" in fn:
            m = _MUTEX_ARG.search(raw)
            return "pthread mutex", m.group(1) if m else ""
        if fn.endswith("lll_lock_wait_private") or fn.endswith("lll_lock_wait"):
            outer = t.frames[i + 1:i + 4]
            if any(any(k in o for k in _MALLOC_FUNCS) for o in outer):
                m = _FUTEX_ARG.search(raw)
                return "malloc arena lock", m.group(1) if m else ""
    return None


def _read_int(text: str) -> int | None:
    m = re.search(r"= (-?\d+)", text)
    return int(m.group(1)) if m else None


def diagnose(pid: int, *, nodes_by_pid: dict[int, str] | None = None, dead_pids: set[int] = frozenset()) -> Diagnosis:
    """Attach to ``pid`` with gdb and say what its threads are blocked on."""
    nodes_by_pid = nodes_by_pid or {}
    text = _gdb(pid, ["thread apply all bt 40"])
    threads = parse_threads(text)
    blocked = []
    for t in threads:
        what = _classify(t)
        if what is None:
            continue
        kind, addr = what
        owner = None
        if kind == "pthread mutex" and addr:
            owner = _read_int(_gdb(pid, [f"print ((int *){addr})[2]"]))   # __data.__owner
        elif kind == "GIL":
            owner = _read_int(_gdb(pid, [
                "print ((PyThreadState *)_PyRuntime.ceval.gil.last_holder._value)->native_thread_id"
            ]))
        owner = owner or None
        blocked.append(BlockedOn(
            tid=t.tid, kind=kind, address=addr, owner_tid=owner,
            owner_node=nodes_by_pid.get(owner) if owner else None,
            owner_dead=bool(owner) and (owner in dead_pids or not procfs.alive(owner)),
        ))
    return Diagnosis(pid, text, threads, blocked)
