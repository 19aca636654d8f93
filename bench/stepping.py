"""Instructions a node process runs in faults/hammer.c's hammer_pairs,
counted by single-stepping it with ptrace on the real CPU (this VM has no
hardware counter for perf, and under valgrind the CPU shows no protection
keys). Used by pkeys_cost and accounting_cost.

The worker prints one JSON line ``{"pid": node process, "entry": address of
hammer_pairs}``, waits for a byte on its stdin, then calls hammer_pairs
``calls`` times. Each call is stepped from its first instruction (a
breakpoint there) to its return; user mode only (the kernel's work is not
counted), a rep-prefixed instruction counts once per iteration.
"""

from __future__ import annotations

import collections
import ctypes
import json
import os
import subprocess
from collections.abc import Callable


class Tracer:
    """ptrace, through libc, from the one thread that attached."""

    SEIZE, INTERRUPT, CONT, STEP, PEEKTEXT, POKETEXT, PEEKUSER, POKEUSER, DETACH = (
        0x4206, 0x4207, 7, 9, 1, 4, 3, 6, 17,
    )  # fmt: skip
    RIP, RSP = 16 * 8, 19 * 8  # offsets in struct user_regs_struct (x86-64)
    WALL = 0x40000000
    MASK = (1 << 64) - 1

    def __init__(self, pid: int):
        self.libc = ctypes.CDLL(None, use_errno=True)
        self.libc.ptrace.argtypes = [ctypes.c_long, ctypes.c_long, ctypes.c_void_p, ctypes.c_void_p]
        self.libc.ptrace.restype = ctypes.c_long
        self.pid = pid

    def __call__(self, req: int, addr: int = 0, data: int = 0) -> int:
        ctypes.set_errno(0)
        r = self.libc.ptrace(req, self.pid, addr, data)
        if r == -1 and ctypes.get_errno():
            e = ctypes.get_errno()
            raise OSError(e, f"ptrace({req}) of {self.pid}: {os.strerror(e)}")
        return r & self.MASK

    def wait(self) -> int:
        _, status = os.waitpid(self.pid, self.WALL)
        if not os.WIFSTOPPED(status):
            raise RuntimeError(f"the traced node process {self.pid} ended (status {status:#x})")
        return status


def _one_call(pt: Tracer, entry: int, max_steps: int, hist: collections.Counter | None) -> int:
    """Steps one call of the function at entry, stopped at its breakpoint,
    to its return: how many instructions (each address's count in hist)."""
    sp = pt(pt.PEEKUSER, pt.RSP)
    ret = pt(pt.PEEKTEXT, sp)
    if hist is not None:
        hist[entry] += 1
    n, sig = 0, 0
    while n < max_steps:
        pt(pt.STEP, 0, sig)
        status = pt.wait()
        sig = os.WSTOPSIG(status)
        if sig != 5 or status >> 16:  # a signal to deliver, or an event stop: not a step
            sig = sig if sig != 5 and status >> 16 == 0 else 0
            continue
        sig = 0
        n += 1
        rip = pt(pt.PEEKUSER, pt.RIP)
        if rip == ret and pt(pt.PEEKUSER, pt.RSP) == sp + 8:
            return n
        if hist is not None:
            hist[rip] += 1  # the next instruction's address: n counts the one before it
    raise RuntimeError(f"hammer_pairs did not return within {max_steps} steps")


def step_calls(
    proc: subprocess.Popen,
    what: str,
    calls: int,
    *,
    max_steps: int = 50_000_000,
    histogram: bool = False,
    on_hello: Callable[[dict], None] | None = None,
) -> tuple[list[int], list[collections.Counter]]:
    """Each of the worker's ``calls`` calls of hammer_pairs stepped: the
    instructions of each, and (``histogram``) how often each address ran.
    ``on_hello`` sees the worker's first line before anything is stepped."""
    assert proc.stdin is not None and proc.stdout is not None
    hello = json.loads(proc.stdout.readline() or b"null")
    if not hello:
        err = proc.stderr.read().decode(errors="replace") if proc.stderr else ""
        raise RuntimeError(f"{what} said nothing:\n{err[-3000:]}")
    if on_hello is not None:
        on_hello(hello)
    pt, entry = Tracer(hello["pid"]), hello["entry"]
    pt(pt.SEIZE)
    pt(pt.INTERRUPT)
    pt.wait()
    word = pt(pt.PEEKTEXT, entry)
    trap = (word & ~0xFF) | 0xCC  # int3 on hammer_pairs' first byte
    pt(pt.POKETEXT, entry, trap)
    pt(pt.CONT)
    proc.stdin.write(b"g")
    proc.stdin.flush()
    counts: list[int] = []
    hists: list[collections.Counter] = []
    for call in range(calls):
        while True:  # to the breakpoint; other stops pass their signal on
            status = pt.wait()
            sig = os.WSTOPSIG(status)
            if sig == 5 and pt(pt.PEEKUSER, pt.RIP) == entry + 1:
                break
            pt(pt.CONT, 0, sig if sig != 5 and status >> 16 == 0 else 0)
        pt(pt.POKETEXT, entry, word)
        pt(pt.POKEUSER, pt.RIP, entry)
        hist: collections.Counter | None = collections.Counter() if histogram else None
        counts.append(_one_call(pt, entry, max_steps, hist))
        if hist is not None:
            hists.append(hist)
        if call < calls - 1:
            pt(pt.POKETEXT, entry, trap)
            pt(pt.CONT)
        else:
            pt(pt.DETACH)
    return counts, hists
