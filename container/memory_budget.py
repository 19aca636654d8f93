"""Memory budgets of node processes (isolated mode, with the allocator
guard): the sizes users write, and the LoadNode extra argument that gives
one node a budget of its own.

A node process whose memory in use would go over its budget ends itself
just before the allocation that would have done it (SIGKILL to itself,
outside the allocator: its heap stays sound for the next process in its
slot), and its CRASHED event says "out of memory: N MiB in use, over its
limit of M MiB (it asked for K MiB more)". What is counted is the allocator
guard's (container/isolated/allocguard/allocguard.c): its malloc'd blocks, glibc's
mmapped ones, its Python objects; not memory it maps itself, its thread
stacks, nor what its libraries allocated before the guard was on.

``--node-memory-limit SIZE`` gives every node process that budget; the extra
argument ``MEMORY_LIMIT`` one node (it wins; 0: none for that node).

Apart from budgets, the container's memory watch (isolated/memory_watch.py)
ends the node process that uses the most when the container's own memory
nears what it may use; the extra argument ``OOM_SCORE_ADJ`` weighs one node
in that choice as the kernel's ``oom_score_adj`` does (-1000 to 1000: its
thousandths of the limit added to its memory; -1000: never this one).
"""

from __future__ import annotations

import re

MEMORY_LIMIT = "cloneguard.memory_limit"
OOM_SCORE_ADJ = "cloneguard.oom_score_adj"
OOM_SCORE_ADJ_RANGE = (-1000, 1000)

_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}
_SIZE = re.compile(r"\s*(\d+(?:\.\d+)?)\s*([kmgt]?)(?:i?b)?\s*", re.IGNORECASE)


def parse_size(value: object) -> int:
    """Bytes, from a whole number of bytes or a text such as ``512M``,
    ``1.5G``, ``800MiB`` (K, M, G, T: powers of 1024). ValueError saying
    what is accepted otherwise."""
    if isinstance(value, bool):
        raise ValueError(f"a size is bytes or a text such as 512M, not {value!r}")
    if isinstance(value, int):
        if value < 0:
            raise ValueError(f"a size is at least 0 bytes, not {value}")
        return value
    match = _SIZE.fullmatch(str(value))
    if match is None:
        raise ValueError(f"a size is bytes or a number with K, M, G or T (512M, 1.5G), not {value!r}")
    return int(float(match.group(1)) * _UNITS[match.group(2).lower()])


def describe(limit_bytes: int) -> str:
    return f"{limit_bytes / (1 << 20):.1f} MiB" if limit_bytes else "none"


def at_death(memory: tuple[int, int] | None) -> str:
    """What a node's death adds to its log line: its process's memory then
    (bytes in use, budget, 0: none, as the guard counted them), or nothing
    where nothing counts it."""
    if memory is None:
        return ""
    in_use, limit = memory
    return f" ({in_use / (1 << 20):.1f} MiB in use" + (f" of its {describe(limit)} budget" if limit else "") + ")"
