"""How deep a CPython 3.11 frame's value stack stands at an instruction,
from its bytecode alone: which words of a dead task's running frame are
references (reclaim.py).

A running frame does not save its stack pointer (interp.c), and the words
past it are stale: the compiler's own rule tells the depth instead. Every
instruction has one stack depth before it, whatever path led there
(CPython's compiler checks it, and sizes ``co_stacksize`` by it), so a walk
of the control flow from the first instruction, adding each instruction's
``dis.stack_effect`` (taken or not taken for a jump), finds the depth
before any instruction. An exception handler starts at its table entry's
depth, plus the offset of the raising instruction when the entry keeps it
(``lasti``), plus the exception.

What a call holds while it runs: PRECALL and CALL (and what 3.11
specialises them to, which run the call inside PRECALL) have ``argc + 2``
inputs at the top (the method or NULL, the callable or self, the
arguments); the words below them were pushed by instructions that are done
and are references for certain. The compiler counts a call's stack effect
as ``-argc`` at PRECALL and ``-1`` at CALL, but PRECALL pops nothing: CALL
runs with its inputs still there, ``argc`` words deeper than the count. A task can die inside the call, or after
it returned, while CALL drops its inputs: those top words are never
counted. For any other instruction nothing of the stack is.
"""

from __future__ import annotations

import dis
from types import CodeType

# 3.11's instructions after which the next one never runs.
_NO_FALLTHROUGH = frozenset(
    dis.opmap[name]
    for name in ("RETURN_VALUE", "RAISE_VARARGS", "RERAISE")
    + ("JUMP_FORWARD", "JUMP_BACKWARD", "JUMP_BACKWARD_NO_INTERRUPT")
)
_JUMPS = frozenset(dis.hasjrel) | frozenset(dis.hasjabs)
_CALL = dis.opmap["CALL"]
_CALLS = frozenset({dis.opmap["PRECALL"], _CALL})


class NotKnown(Exception):
    """The bytecode does not give one depth there."""


# A generator's first instruction: when it resumes, the value sent is on
# its stack (the POP_TOP after it drops it); dis counts 0.
_RETURN_GENERATOR = dis.opmap["RETURN_GENERATOR"]


def _effect(ins: dis.Instruction, jump: bool) -> int:
    if ins.opcode == _RETURN_GENERATOR:
        return 1
    arg = ins.arg if ins.opcode >= dis.HAVE_ARGUMENT else None
    return dis.stack_effect(ins.opcode, arg, jump=jump)


def depths(code: CodeType) -> dict[int, int]:
    """The stack depth before each reachable instruction, by byte offset."""
    instructions = {ins.offset: ins for ins in dis.get_instructions(code)}
    offsets = sorted(instructions)
    following = dict(zip(offsets, offsets[1:], strict=False))  # the last has none
    depth: dict[int, int] = {}
    work: list[tuple[int, int]] = [(0, 0)]
    for entry in dis._parse_exception_table(code):  # type: ignore[attr-defined]  # 3.11's table, no public reader
        work.append((entry.target, entry.depth + int(entry.lasti) + 1))
    while work:
        offset, d = work.pop()
        if offset in depth:
            if depth[offset] != d:
                raise NotKnown(f"{code.co_qualname}: depth {depth[offset]} and {d} at offset {offset}")
            continue
        ins = instructions.get(offset)
        if ins is None or d < 0:
            raise NotKnown(f"{code.co_qualname}: no instruction or a negative depth at offset {offset}")
        depth[offset] = d
        if ins.opcode in _JUMPS:
            work.append((ins.argval, d + _effect(ins, jump=True)))
        if ins.opcode not in _NO_FALLTHROUGH and offset in following:
            work.append((following[offset], d + _effect(ins, jump=False)))
    return depth


def call_stack(code: CodeType, unit: int, words: list[int]) -> tuple[list[int], list[int]]:
    """A running frame's value stack (``words``, bottom first) at the
    instruction ``unit`` code units into ``code``: (the words that are
    references for certain, the words that may be). Only below a call's
    inputs is anything certain."""
    offset = unit * 2
    ins = next((i for i in dis.get_instructions(code) if i.offset == offset), None)
    if ins is None or ins.opcode not in _CALLS:
        return [], words
    try:
        d = depths(code).get(offset)
    except NotKnown:
        return [], words
    argc = ins.arg or 0
    inputs = argc + 2
    if d is not None and ins.opcode == _CALL:
        d += argc
    if d is None or d > len(words) or d < inputs:
        return [], words
    return words[: d - inputs], words[d - inputs : d]
