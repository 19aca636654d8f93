"""Kill clone children at random instants and see whether the process goes on.

Run as a program, it is the *container side*: a CloneCore with the given
mitigations, a Python counter thread of its own, a long-lived sibling child
that counts too, and a loop that spawns a victim child, says so on stdout,
waits for its death and checks that both counters still advance. The victim
(``--victim``):

``loop``      a tight Python loop: it holds, waits for and hands over the
              GIL all the time (what the GIL and condvar repairs are for);
``pymalloc``  Python objects of <= 512 B (Python's object allocator, under the
              GIL: the guard's pools of each process, or with
              ``--python-pools 0`` CPython's pymalloc), tracked by the
              garbage collector;
``malloc``    the malloc hammer in C (GIL released): 16 B .. 2 MiB blocks,
              one in eight handed to the container's counter thread, which
              frees them (what the allocator guard is for). The sibling then
              allocates blocks from malloc too.

``run()`` is the *outside*: it runs that program in subprocesses (with the
allocator guard and jemalloc preloaded as asked), SIGKILLs each victim
itself after a random 0-``max_delay_ms`` (from another process, so the kill
lands wherever the victim is), and counts per kill: survived / hung (no
progress within ``hang_s``: diagnosed with the harness's gdb diagnosis, then
the subprocess is killed and a fresh one takes over) / crashed (the
subprocess died). Only the subprocess can freeze.

    python -m cloneguard.bench.random_kill --kills 300 --victim malloc
    python -m cloneguard.bench.random_kill --kills 300 --victim malloc --jemalloc
    python -m cloneguard.bench.random_kill --kills 100 --gil-repair 0
    python -m cloneguard.bench.random_kill --kills 3000 --victim pymalloc [--python-pools 0] [--container-gc 0]
                                           [--interp-repair 0]

A ``crashed`` run (the container side died) is the container death the
interpreter mitigations are for (container/isolated/clonecore/interp.c, pyalloc.c).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import random
import select
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

PROGRESS_TIMEOUT_S = 2.0


# --------------------------------------------------------------------------
# the container side


def _victim_loop() -> None:
    x = 0
    while True:  # small ints only: no allocation
        x = (x + 1) & 255


def _victim_pymalloc() -> None:
    junk = []
    while True:  # allocates (pymalloc) all the time
        junk.append([str(i) for i in range(20)])
        if len(junk) > 50:
            junk.clear()


RING = 5  # the malloc hammer's ring this bench uses


def _victim_malloc() -> None:
    from cloneguard.faults._hammer import lib as hammer

    hammer.hammer_run(RING, int.from_bytes(os.urandom(8), "little") | 1)


VICTIMS = {"loop": _victim_loop, "pymalloc": _victim_pymalloc, "malloc": _victim_malloc}


def _serve(args) -> int:
    from cloneguard.container import allocator

    allocator.glibc_arena_per_task()  # before a second thread starts
    from cloneguard.container.isolated.core import CloneCore, stop_requested
    from cloneguard.faults._hammer import lib as hammer

    counter = [0]
    sibling_count = [0]
    mallocs = args.victim == "malloc"

    def count() -> None:
        while True:
            counter[0] += 1
            if mallocs and counter[0] % 64 == 0:
                hammer.drain_some(RING)  # frees the victims' blocks

    def sibling() -> None:
        while not stop_requested():
            sibling_count[0] += 1
            if mallocs:
                bytes(1000 + sibling_count[0] % 4000)  # > 512 B: malloc

    def advances(cell, timeout: float) -> bool:
        start = cell[0]
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            time.sleep(0.005)
            if cell[0] != start:
                return True
        return False

    threading.Thread(target=count, daemon=True).start()
    core = CloneCore(
        gil_repair=bool(args.gil_repair),
        condvar_repair=bool(args.condvar_repair),
        container_gc=bool(args.container_gc),
        interp_repair=bool(args.interp_repair),
        crash_report=False,
        alloc_guard=allocator.guard_loaded(),
    )
    sib = core.spawn(sibling)
    victim = VICTIMS[args.victim]
    print(f"ready {sib.pid}", flush=True)
    for i in range(args.kills):
        child = core.spawn(victim)
        print(f"spawned {i} {child.pid}", flush=True)  # the outside kills it
        death = core.wait(child, 30)
        if death is None:
            return _stuck(i, "no-death")
        core.release(child)
        if not advances(counter, PROGRESS_TIMEOUT_S):
            return _stuck(i, "counter")
        if not advances(sibling_count, PROGRESS_TIMEOUT_S):
            return _stuck(i, "sibling")
        print(
            f"ok {i} {int(death.repairs)} {death.exit_signal} {int(death.alloc_quarantined)} {int(death.py_abandoned)}",
            flush=True,
        )
    core.request_stop(sib)
    core.wait(sib, PROGRESS_TIMEOUT_S)
    print("done", flush=True)
    os._exit(0)  # the dead children's leftovers must not be finalized


def _stuck(i: int, what: str) -> int:
    """Say what stopped and wait, stuck as we are, for the outside's
    diagnosis (and its SIGKILL)."""
    print(f"stuck {i} {what}", flush=True)
    while True:
        time.sleep(3600)


# --------------------------------------------------------------------------
# the outside


@dataclass
class Result:
    settings: dict
    kills: int = 0
    survived: int = 0
    hung: int = 0
    crashed: int = 0
    repairs: collections.Counter = field(default_factory=collections.Counter)
    quarantined: int = 0  # victims that died inside the allocator
    py_abandoned: int = 0  # ... inside Python's object allocator (pyalloc.c)
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)
    hangs: list[str] = field(default_factory=list)  # diagnosis summaries

    def line(self) -> str:
        rep = ", ".join(f"{k} {v}" for k, v in sorted(self.repairs.items())) or "none"
        return (
            f"{self.settings}: {self.survived}/{self.kills} survived, "
            f"{self.hung} hung, {self.crashed} crashed "
            f"({self.seconds:.0f} s; repairs: {rep}; {self.quarantined} died inside malloc, "
            f"{self.py_abandoned} inside Python's object allocator)"
        )


def _serve_env(alloc_guard: bool, jemalloc: bool, python_pools: bool) -> dict[str, str]:
    """The container side's environment: the guard and jemalloc preloaded as asked."""
    from cloneguard.container import allocator

    env = dict(os.environ)
    preload = [allocator.GUARD_PATH] if alloc_guard else []
    if jemalloc:
        path = allocator.jemalloc_path()
        if path is None:
            raise SystemExit("random_kill: jemalloc asked for, but libjemalloc2 is not installed")
        preload.append(path)
    env["LD_PRELOAD"] = " ".join(preload)
    if not python_pools:
        env[allocator.PY_POOLS_OFF] = "0"
    return env


@dataclass
class _Watch:
    """What the outside saw of one subprocess (its lines on stdout)."""

    rng: random.Random
    max_delay_ms: float
    pids: dict[int, str] = field(default_factory=dict)  # its tasks: the sibling and each victim
    dead: set[int] = field(default_factory=set)  # the victims killed
    ready: bool = False
    last: float = field(default_factory=time.monotonic)  # its last line
    outcome: str | None = None  # "hung", "exited" or "done"

    def line(self, words: list[str], res: Result) -> None:
        """One line of the container side's: count it, kill a victim it spawned."""
        from cloneguard.container.isolated.core_events import Repair

        self.last = time.monotonic()
        if words[0] == "ready":
            self.ready = True
            self.pids[int(words[1])] = "sibling"
        elif words[0] == "spawned":
            self.pids[int(words[2])] = f"victim {words[1]}"
            self.dead.add(int(words[2]))
            time.sleep(self.rng.uniform(0, self.max_delay_ms / 1000))
            try:
                os.kill(int(words[2]), signal.SIGKILL)
            except ProcessLookupError:
                pass
            self.last = time.monotonic()
        elif words[0] == "ok":
            res.kills += 1
            res.survived += 1
            for name in Repair(int(words[2])).names():
                res.repairs[name] += 1
            res.quarantined += int(words[4])
            res.py_abandoned += int(words[5])
        elif words[0] == "stuck":
            res.notes.append(" ".join(words))
            self.outcome = "hung"
        elif words[0] == "done":
            self.outcome = "done"


def _watch(proc: subprocess.Popen[bytes], w: _Watch, res: Result, hang_s: float) -> None:
    """Read the subprocess's lines until it is done, exits, or makes no
    progress for hang_s (60 s until it is ready)."""
    assert proc.stdout is not None  # Popen(stdout=PIPE)
    buf = b""
    while w.outcome is None:
        limit = (60.0 if not w.ready else hang_s) - (time.monotonic() - w.last)
        r, _, _ = select.select([proc.stdout], [], [], max(0.0, limit))
        if not r:
            w.outcome = "hung"
            break
        chunk = os.read(proc.stdout.fileno(), 65536)
        if not chunk:
            w.outcome = "exited"
            break
        buf += chunk
        while b"\n" in buf:
            line, buf = buf.split(b"\n", 1)
            w.line(line.decode().split(), res)


def _one_run(
    argv: list[str], env: dict[str, str], res: Result, w: _Watch, hang_s: float, hang_file: str | None
) -> tuple[int, str]:
    """One subprocess, watched until it ends (a hang diagnosed into res and
    hang_file, then killed); its exit status and stderr."""
    from cloneguard.harness import diagnose

    proc = subprocess.Popen(
        argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env=env,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
        start_new_session=True,
    )
    assert proc.stdout is not None and proc.stderr is not None  # PIPE
    w.last = time.monotonic()
    try:
        _watch(proc, w, res, hang_s)
        if w.outcome == "hung" and w.ready:
            res.kills += 1
            res.hung += 1
            if diagnose.gdb_available():
                d = diagnose.diagnose(proc.pid, nodes_by_pid=w.pids, dead_pids=w.dead)
                res.hangs.append(d.summary())
                if hang_file:
                    with open(hang_file, "w") as out:
                        out.write(d.summary() + "\n\n" + d.stacks_text)
    finally:  # whatever happened reading it (an error of ours too), it goes
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    rc = proc.returncode
    err = proc.stderr.read().decode(errors="replace")
    proc.stdout.close()
    proc.stderr.close()
    return rc, err


def run(
    kills: int,
    *,
    gil_repair: bool = True,
    condvar_repair: bool = True,
    victim: str = "loop",
    alloc_guard: bool = True,
    jemalloc: bool = False,
    python_pools: bool = True,
    container_gc: bool = True,
    interp_repair: bool = True,
    seed: int = 1,
    hang_s: float = 3.0,
    max_delay_ms: float = 20.0,
    budget_s: float | None = None,
    max_hangs: int | None = None,
    diagnose_dir: str | None = None,
) -> Result:
    """``kills`` random kills in as many fresh subprocesses as needed (fewer
    if ``budget_s`` runs out or ``max_hangs`` hangs were seen)."""
    res = Result(
        {
            "gil_repair": gil_repair,
            "condvar_repair": condvar_repair,
            "victim": victim,
            "alloc_guard": alloc_guard,
            "jemalloc": jemalloc,
            "python_pools": python_pools and alloc_guard,
            "container_gc": container_gc,
            "interp_repair": interp_repair,
        }
    )
    env = _serve_env(alloc_guard, jemalloc, python_pools)
    t0 = time.monotonic()
    rng = random.Random(seed)
    run_no = 0
    while res.kills < kills:
        if budget_s is not None and time.monotonic() - t0 > budget_s:
            res.notes.append("time budget used up")
            break
        if max_hangs is not None and res.hung + res.crashed >= max_hangs:
            break
        run_no += 1
        argv = [
            sys.executable,
            "-m",
            "cloneguard.bench.random_kill",
            "--serve",
            "--kills",
            str(kills - res.kills),
            "--gil-repair",
            str(int(gil_repair)),
            "--condvar-repair",
            str(int(condvar_repair)),
            "--container-gc",
            str(int(container_gc)),
            "--interp-repair",
            str(int(interp_repair)),
            "--victim",
            victim,
        ]
        w = _Watch(rng, max_delay_ms)
        hang_file = os.path.join(diagnose_dir, f"hang-{seed}-{run_no}.txt") if diagnose_dir else None
        rc, err = _one_run(argv, env, res, w, hang_s, hang_file)
        if w.outcome == "exited":
            if not w.ready:
                raise RuntimeError(f"random_kill did not start (rc {rc}):\n{err[-3000:]}")
            if rc != 0:
                res.kills += 1
                res.crashed += 1
                res.notes.append(f"run {run_no}: exit {rc}: {err.strip()[-300:]}")
    res.seconds = time.monotonic() - t0
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--kills", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1, help="for the kill delays")
    ap.add_argument("--gil-repair", type=int, default=1)
    ap.add_argument("--condvar-repair", type=int, default=1)
    ap.add_argument(
        "--victim", choices=sorted(VICTIMS), default="loop", help="what the victim does (default: %(default)s)"
    )
    ap.add_argument("--alloc-guard", type=int, default=1, help="preload the allocator guard (default 1)")
    ap.add_argument("--jemalloc", action="store_true", help="preload jemalloc too")
    ap.add_argument(
        "--python-pools",
        type=int,
        default=1,
        help="Python objects from the guard's pools of each process (default 1; 0: pymalloc)",
    )
    ap.add_argument(
        "--container-gc", type=int, default=1, help="collect garbage only on a container thread (default 1)"
    )
    ap.add_argument(
        "--interp-repair", type=int, default=1, help="after a death with the GIL, mend the interpreter (default 1)"
    )
    ap.add_argument("--max-delay-ms", type=float, default=20.0)
    ap.add_argument("--hang-s", type=float, default=3.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--diagnose", metavar="DIR", help="gdb stacks of hung runs into DIR")
    args = ap.parse_args(argv)
    if args.serve:
        return _serve(args)
    res = run(
        args.kills,
        gil_repair=bool(args.gil_repair),
        condvar_repair=bool(args.condvar_repair),
        victim=args.victim,
        alloc_guard=bool(args.alloc_guard),
        jemalloc=args.jemalloc,
        python_pools=bool(args.python_pools),
        container_gc=bool(args.container_gc),
        interp_repair=bool(args.interp_repair),
        seed=args.seed,
        hang_s=args.hang_s,
        max_delay_ms=args.max_delay_ms,
        diagnose_dir=args.diagnose,
    )
    print(json.dumps(res.__dict__, default=dict) if args.json else res.line())
    for note in res.notes[:20]:
        print("  ", note)
    for hang in res.hangs[:20]:
        print("   hang:", hang)
    return 0


if __name__ == "__main__":
    sys.exit(main())
