"""What /proc says about processes: groups, states, parents, threads."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class ProcStat:
    pid: int
    comm: str
    state: str
    ppid: int
    pgrp: int
    session: int
    num_threads: int
    cpu_ticks: int  # utime + stime, in clock ticks (a process's: all its threads')


def _stat_fields(path: str) -> tuple[str, list[str]] | None:
    """(comm, the fields after it: [0] is field 3, state) of a stat file."""
    try:
        with open(path, "rb") as f:
            raw = f.read().decode(errors="replace")
    except (FileNotFoundError, ProcessLookupError):
        return None
    # comm is in parentheses and may itself contain spaces or ')'.
    head, _, rest = raw.rpartition(")")
    return head.partition("(")[2], rest.split()


def _cpu_ticks(fields: list[str]) -> int:
    return int(fields[11]) + int(fields[12])  # utime, stime (fields 14, 15)


def stat(pid: int) -> ProcStat | None:
    read = _stat_fields(f"/proc/{pid}/stat")
    if read is None:
        return None
    comm, fields = read
    return ProcStat(
        pid=pid,
        comm=comm,
        state=fields[0],
        ppid=int(fields[1]),
        pgrp=int(fields[2]),
        session=int(fields[3]),
        num_threads=int(fields[17]),
        cpu_ticks=_cpu_ticks(fields),
    )


def threads(pid: int) -> dict[int, tuple[str, int]]:
    """Every thread of ``pid``: tid -> (its name, its CPU time: user +
    system, in clock ticks)."""
    out: dict[int, tuple[str, int]] = {}
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except (FileNotFoundError, ProcessLookupError):
        return out
    for tid in tids:
        read = _stat_fields(f"/proc/{pid}/task/{tid}/stat")
        if read is not None:
            out[int(tid)] = (read[0], _cpu_ticks(read[1]))
    return out


def thread_cpu_ticks(pid: int) -> dict[int, int]:
    """CPU time (user + system, in clock ticks) of every thread of ``pid``."""
    return {tid: ticks for tid, (_, ticks) in threads(pid).items()}


def all_stats() -> list[ProcStat]:
    out = []
    for name in os.listdir("/proc"):
        if name.isdigit():
            st = stat(int(name))
            if st is not None:
                out.append(st)
    return out


def pids_in_group(pgid: int) -> list[int]:
    return sorted(st.pid for st in all_stats() if st.pgrp == pgid)


def zombies_of(ppid: int) -> list[int]:
    return sorted(st.pid for st in all_stats() if st.ppid == ppid and st.state == "Z")


def children_of(ppid: int) -> list[int]:
    return sorted(st.pid for st in all_stats() if st.ppid == ppid)


def wait_gone(paths: list, timeout: float) -> list:
    """Poll until none of ``paths`` exists; those still there at ``timeout``."""
    deadline = time.monotonic() + timeout
    while (left := [p for p in paths if os.path.exists(p)]) and time.monotonic() < deadline:
        time.sleep(0.05)
    return left


def wait_group_empty(pgid: int, timeout: float) -> bool:
    """Poll until no process is left in ``pgid``; False on timeout."""
    deadline = time.monotonic() + timeout
    while pids_in_group(pgid):
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def status_field(pid: int, key: str) -> str | None:
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return line.split(":", 1)[1].strip()
    except FileNotFoundError:
        return None
    return None


def rss_kib(pid: int) -> int:
    """The resident memory of ``pid`` in KiB (its VmRSS; a process sharing
    an address space shows all of it); ProcessLookupError if it is gone."""
    field = status_field(pid, "VmRSS")
    if field is None:
        raise ProcessLookupError(f"pid {pid} has no VmRSS (gone, or a zombie)")
    return int(field.split()[0])


def lasting_fds(pid: int, readings: int = 3, apart: float = 0.05) -> dict[int, str]:
    """The open fds of ``pid`` (fd: what it names) present in each of
    ``readings`` readings ``apart`` seconds apart: what it keeps open. An
    isolated container opens /proc files for a moment on its own (the lock
    doctor reads its children's tasks on its own schedule), so one listing
    can hold an fd that is gone a moment later; a leaked fd stays."""
    kept: dict[int, str] | None = None
    for i in range(readings):
        if i:
            time.sleep(apart)
        now = {}
        for name in os.listdir(f"/proc/{pid}/fd"):
            try:
                now[int(name)] = os.readlink(f"/proc/{pid}/fd/{name}")
            except FileNotFoundError:
                continue  # closed between the listing and the read
        kept = now if kept is None else {fd: t for fd, t in kept.items() if now.get(fd) == t}
    return kept or {}


_SYS_KCMP = 312  # x86_64
_KCMP_VM = 1
SYS_FUTEX = 202  # x86_64


def syscall_now(tid: int) -> tuple[int, int] | None:
    """(number, first argument) of the system call the task sleeps in
    (/proc/<tid>/syscall: for futex(2), the futex word's address); None
    while it runs, when it is in none, or is gone."""
    try:
        with open(f"/proc/{tid}/syscall") as f:
            fields = f.read().split()
    except OSError:
        return None
    if len(fields) < 2 or not fields[0].isdigit():  # "running", or "-1 <sp> <pc>" outside a call
        return None
    return int(fields[0]), int(fields[1], 16)


def same_address_space(pid1: int, pid2: int) -> bool:
    """kcmp(2) KCMP_VM: do the two processes share one mm? (needs ptrace rights)"""
    import ctypes

    libc = ctypes.CDLL(None, use_errno=True)
    rc = libc.syscall(_SYS_KCMP, pid1, pid2, _KCMP_VM, 0, 0)
    if rc < 0:
        err = ctypes.get_errno()
        raise OSError(err, f"kcmp({pid1}, {pid2}, KCMP_VM): {os.strerror(err)}")
    return rc == 0


def cgroup_dirs_named(name: str) -> list:
    """Directories called ``name`` at the top of any mounted cgroup hierarchy."""
    from pathlib import Path

    found = []
    with open("/proc/self/mounts") as f:
        for line in f:
            parts = line.split()
            if len(parts) > 2 and parts[2] in ("cgroup", "cgroup2"):
                d = Path(parts[1]) / name
                if d.is_dir():
                    found.append(d)
    return found


def task_facts(tid: int) -> str:
    """What /proc says of a task nobody attached to: its state, its thread
    group, and the innermost kernel frames it sleeps in ("" if gone)."""
    state = status_field(tid, "State")
    if state is None:
        return ""
    tgid = status_field(tid, "Tgid")
    try:
        with open(f"/proc/{tid}/stack") as f:
            frames = [line.split("] ", 1)[-1].split("+")[0] for line in f.read().splitlines()[:4]]
    except OSError:
        frames = []
    facts = f"state {state}, thread group {tgid}"
    return facts + (f", in the kernel at {' < '.join(frames)}" if frames else "")


def alive(pid: int) -> bool:
    """The task exists and is not a zombie."""
    st = stat(pid)
    return st is not None and st.state != "Z"
