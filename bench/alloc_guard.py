"""What the allocator guard costs per malloc/free, and per block handed back.

Each configuration runs in a fresh worker process (python -m
cloneguard.bench.alloc_guard --worker ...) with the preload it needs; the loops are in
C (faults/hammer.c), so the figures are the allocator's, not Python's:

* a malloc/free pair of 64 B and 4 KiB by a container thread and by a
  node process (clone child), without the guard, with it preloaded but not
  started (what a process pays before ``--isolated`` starts it), and with
  it on;
* a filled block of each size in a node process, asked for by its own
  code (malloc, memcpy) or by the stack (the C library's strndup): with the
  guard on, the second comes from the slot's shared arena (the split);
* free() of a node's block by the container (the guard hands it back: one
  CAS), and the owner's later freeing of those blocks, per block.

    python -m cloneguard.bench.alloc_guard [--pairs 2000000] [--blocks 200000] [--repeat 5] [--pkeys]
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys

from cloneguard.harness.process import REPO_ROOT

from .cli import arg_parser, command_line, finish
from .results import Result, Table

CONFIGS = [
    # (label, preload guard, activate guard, jemalloc)
    ("glibc, no guard", False, False, False),
    ("glibc, guard preloaded, off", True, False, False),
    ("glibc, guard on", True, True, False),
    ("jemalloc, no guard", False, False, True),
    ("jemalloc, guard preloaded, off", True, False, True),
    ("jemalloc, guard on", True, True, True),
]
# The guard with node heaps under protection keys (--pkeys: heapkeys.c);
# measured only where the CPU has them (--pkeys), beside "jemalloc, guard on".
KEYED = ("jemalloc, guard on, keys", True, True, True)
SIZES = (64, 4096)


def _worker(activate: bool, pairs: int, blocks: int, repeat: int) -> dict:
    from cloneguard.container import allocator

    allocator.glibc_arena_per_task()
    from cloneguard.container.isolated.core import CloneCore
    from cloneguard.faults._hammer import ffi, lib

    out: dict[str, list[float]] = {}

    def add(key: str, ns: int, n: int) -> None:
        out.setdefault(key, []).append(ns / n)

    with CloneCore(alloc_guard=activate) as core:

        def in_child(fn) -> None:
            child = core.spawn(fn)
            death = core.wait(child, 60)
            assert death is not None and death.exit_code == 0
            core.release(child)

        for _ in range(repeat):
            for size in SIZES:
                add(f"pair {size} B, container thread", lib.hammer_pairs(size, pairs), pairs)
                in_child(lambda size=size: add(f"pair {size} B, node process", lib.hammer_pairs(size, pairs), pairs))
                # The split (allocguard.c): a block the stack asks for comes
                # from the slot's shared arena, one of the node's own code
                # from its own; the same block, filled, both ways.
                for whose, stack in (("its own code", 0), ("the stack", 1)):
                    in_child(
                        lambda size=size, whose=whose, stack=stack: add(
                            f"filled pair {size} B, node process, asked by {whose}",
                            lib.hammer_copy_pairs(size, pairs, stack),
                            pairs,
                        )
                    )
            arr = ffi.new("void *[]", blocks)
            in_child(lambda arr=arr: lib.hammer_alloc_many(arr, 256, blocks))
            add("free of a node's 256 B block by the container", lib.hammer_free_many(arr, blocks), blocks)
            # The next child in that context frees them into its arena at
            # its first allocation (with the guard; without, they are freed).
            in_child(
                lambda: add("owner frees what was handed back (first malloc after)", lib.hammer_pairs(64, 1), blocks)
            )
    return out


def measure_config(
    label: str, preload: bool, activate: bool, jemalloc: bool, pairs: int, blocks: int, repeat: int
) -> dict[str, list[float]]:
    """ns per operation, each measure's repeats, of one configuration (a
    row of CONFIGS, or KEYED), in a fresh worker process with its preload."""
    from cloneguard.container import allocator

    env = dict(os.environ)
    env["LD_PRELOAD"] = " ".join(
        ([allocator.GUARD_PATH] if preload else []) + ([allocator.jemalloc_path() or ""] if jemalloc else [])
    )
    if label == KEYED[0]:
        env["CLONEGUARD_PKEYS"] = "1"  # what the container's --pkeys sets (heapkeys.c)
    else:
        env.pop("CLONEGUARD_PKEYS", None)
    worker = [str(int(activate)), str(pairs), str(blocks), str(repeat)]
    proc = subprocess.run(
        [sys.executable, "-m", "cloneguard.bench.alloc_guard", "--worker", *worker],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO_ROOT,
        timeout=1800,
    )
    if proc.returncode != 0:
        raise SystemExit(f"worker ({label}) failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = arg_parser("alloc_guard", __doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2_000_000)
    parser.add_argument("--blocks", type=int, default=200_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument(
        "--pkeys",
        action="store_true",
        help="also measure the guard with node heaps under memory protection keys (needs a CPU with PKU)",
    )
    parser.add_argument("--worker", nargs=4, help=argparse_hidden())
    args = parser.parse_args(argv)
    if args.worker:
        activate, pairs, blocks, repeat = (int(x) for x in args.worker)
        print(json.dumps(_worker(bool(activate), pairs, blocks, repeat)))
        return 0
    configs = list(CONFIGS)
    if args.pkeys:
        from cloneguard.container.isolated import pkeys

        why = pkeys.probe().unavailable
        if why:
            raise SystemExit(f"--pkeys cannot be measured here: {why}")
        configs.append(KEYED)
    raw = {
        label: measure_config(label, preload, activate, jemalloc, args.pairs, args.blocks, args.repeat)
        for label, preload, activate, jemalloc in configs
    }
    measures = list(next(iter(raw.values())))
    table = Table("ns per operation (median of the repeats)", ["measure", *[c[0] for c in configs]])
    for m in measures:
        table.add(m, *[f"{statistics.median(raw[c[0]][m]):.1f}" for c in configs])
    result = Result(
        name="alloc_guard",
        title="Allocator guard: cost per malloc/free",
        command=command_line(
            "alloc_guard", {"pairs": args.pairs, "blocks": args.blocks, "repeat": args.repeat, "pkeys": args.pkeys}
        ),
        params=vars(args) | {"out": str(args.out)},
        tables=[table],
        goals=[],
        notes=[
            "Loops in C (faults/hammer.c: hammer_pairs, hammer_alloc_many, hammer_free_many), "
            "each configuration in a fresh process with its own LD_PRELOAD.",
            "'guard preloaded, off': the interposer is in place but cga_activate was not called "
            "(isolated mode not started): every call passes straight through.",
            "The last row is the first allocation of the next node process in the same context "
            "divided by the number of blocks it frees then; without the guard nothing was handed "
            "back, and the row is one malloc/free pair spread over that many blocks.",
            *(
                [
                    "'keys': the guard with CLONEGUARD_PKEYS=1 (the container's --pkeys): a node process's "
                    "malloc is routed by its caller (keyed arena or shared) and runs under its PKRU; "
                    "the handed-back free opens every key for its one store."
                ]
                if args.pkeys
                else []
            ),
        ],
        summary=[],
        raw=raw,
        cleanup=[],
    )
    finish(result, args.out)
    return 0


def argparse_hidden() -> str:
    import argparse

    return argparse.SUPPRESS


if __name__ == "__main__":
    sys.exit(main())
