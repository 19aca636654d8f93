"""Kill children at random instants and see whether the process goes on.

Run as a program, it is the *container side*: a CloneCore with the given
mitigations, a Python counter thread of its own, a long-lived sibling child
that counts too, and a loop that spawns a victim child running a tight Python
loop (so it holds, waits for and hands over the GIL all the time), says so on
stdout, waits for its death and checks that both counters still advance.

``run()`` is the *outside*: it runs that program in subprocesses, SIGKILLs
each victim itself after a random 0-``max_delay_ms`` (from another process,
so the kill lands wherever the victim is, the GIL held or not), and counts
per kill: survived / hung (no progress within ``hang_s``: the subprocess is
killed and a fresh one takes over) / crashed (the subprocess died).  Only the
subprocess can freeze.

    python -m container.isolated.killbench --kills 300 --gil-repair 0
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
    while True:                 # small ints only: no allocation
        x = (x + 1) & 255


def _victim_alloc() -> None:
    junk = []
    while True:                 # allocates (pymalloc) all the time
        junk.append([str(i) for i in range(20)])
        if len(junk) > 50:
            junk.clear()


def _serve(args) -> int:
    from container.isolated.core import CloneCore, stop_requested

    counter = [0]
    sibling_count = [0]

    def count() -> None:
        while True:
            counter[0] += 1

    def sibling() -> None:
        while not stop_requested():
            sibling_count[0] += 1

    def advances(cell, timeout: float) -> bool:
        start = cell[0]
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            time.sleep(0.005)
            if cell[0] != start:
                return True
        return False

    threading.Thread(target=count, daemon=True).start()
    core = CloneCore(gil_repair=bool(args.gil_repair),
                     condvar_repair=bool(args.condvar_repair),
                     crash_report=False)
    sib = core.spawn(sibling)
    victim = _victim_alloc if args.alloc else _victim_loop
    print("ready", flush=True)
    for i in range(args.kills):
        child = core.spawn(victim)
        print(f"spawned {i} {child.pid}", flush=True)    # the outside kills it
        death = core.wait(child, 30)
        if death is None:
            print(f"stuck {i} no-death", flush=True)
            return 3
        core.release(child)
        if not advances(counter, PROGRESS_TIMEOUT_S):
            print(f"stuck {i} counter", flush=True)
            return 3
        if not advances(sibling_count, PROGRESS_TIMEOUT_S):
            print(f"stuck {i} sibling", flush=True)
            return 3
        print(f"ok {i} {int(death.repairs)} {death.exit_signal}", flush=True)
    core.request_stop(sib)
    core.wait(sib, PROGRESS_TIMEOUT_S)
    print("done", flush=True)
    os._exit(0)   # the dead children's leftovers must not be finalized


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
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    def line(self) -> str:
        rep = ", ".join(f"{k} {v}" for k, v in sorted(self.repairs.items())) or "none"
        return (f"{self.settings}: {self.survived}/{self.kills} survived, "
                f"{self.hung} hung, {self.crashed} crashed "
                f"({self.seconds:.0f} s; repairs: {rep})")


def run(kills: int, *, gil_repair: bool = True, condvar_repair: bool = True,
        alloc: bool = False, seed: int = 1, hang_s: float = 3.0,
        max_delay_ms: float = 20.0, budget_s: float | None = None,
        max_hangs: int | None = None, diagnose_dir: str | None = None) -> Result:
    """``kills`` random kills in as many fresh subprocesses as needed (fewer
    if ``budget_s`` runs out or ``max_hangs`` hangs were seen)."""
    from container.isolated.events import Repair

    res = Result({"gil_repair": gil_repair, "condvar_repair": condvar_repair,
                  "alloc": alloc})
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
        argv = [sys.executable, "-m", "container.isolated.killbench", "--serve",
                "--kills", str(kills - res.kills),
                "--gil-repair", str(int(gil_repair)),
                "--condvar-repair", str(int(condvar_repair))] + (
                    ["--alloc"] if alloc else [])
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                cwd=os.path.dirname(os.path.dirname(os.path.dirname(
                                    os.path.abspath(__file__)))),
                                start_new_session=True)
        buf = b""
        ready = False
        last = time.monotonic()
        outcome = None
        while outcome is None:
            limit = (60.0 if not ready else hang_s) - (time.monotonic() - last)
            r, _, _ = select.select([proc.stdout], [], [], max(0.0, limit))
            if not r:
                outcome = "hung"
                break
            chunk = os.read(proc.stdout.fileno(), 65536)
            if not chunk:
                outcome = "exited"
                break
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                words = line.decode().split()
                last = time.monotonic()
                if words[0] == "ready":
                    ready = True
                elif words[0] == "spawned":
                    time.sleep(rng.uniform(0, max_delay_ms / 1000))
                    try:
                        os.kill(int(words[2]), signal.SIGKILL)
                    except ProcessLookupError:
                        pass
                    last = time.monotonic()
                elif words[0] == "ok":
                    res.kills += 1
                    res.survived += 1
                    for name in Repair(int(words[2])).names():
                        res.repairs[name] += 1
                elif words[0] == "stuck":
                    res.notes.append(" ".join(words))
                elif words[0] == "done":
                    outcome = "done"
        if outcome == "hung" and ready:
            res.kills += 1
            res.hung += 1
            if diagnose_dir:
                _diagnose(proc.pid, os.path.join(diagnose_dir, f"hang-{seed}-{run_no}.txt"))
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        rc = proc.wait()
        err = proc.stderr.read().decode(errors="replace")
        if outcome == "exited":
            if not ready:
                raise RuntimeError(f"killbench did not start (rc {rc}):\n{err[-3000:]}")
            if rc < 0 or rc not in (0, 3):
                res.kills += 1
                res.crashed += 1
                res.notes.append(f"run {run_no}: exit {rc}: {err.strip()[-300:]}")
            elif rc == 3:
                res.kills += 1
                res.hung += 1
        proc.stdout.close()
        proc.stderr.close()
    res.seconds = time.monotonic() - t0
    return res


def _diagnose(pid: int, path: str) -> None:
    """Every task's native stack (gdb), for a hung container side."""
    with open(path, "w") as out:
        tasks = sorted(int(t) for t in os.listdir(f"/proc/{pid}/task"))
        kids = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True,
                              text=True).stdout.split()
        for target in [pid, *map(int, kids)]:
            out.write(f"==== gdb -p {target} (tasks {tasks if target == pid else ''})\n")
            out.flush()
            subprocess.run(["gdb", "-p", str(target), "-batch", "-iex", "set auto-load safe-path /",
                            "-ex", "thread apply all bt 30"], stdout=out, stderr=subprocess.STDOUT,
                           timeout=120)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--kills", type=int, default=100)
    ap.add_argument("--seed", type=int, default=1, help="for the kill delays")
    ap.add_argument("--gil-repair", type=int, default=1)
    ap.add_argument("--condvar-repair", type=int, default=1)
    ap.add_argument("--alloc", action="store_true",
                    help="the victim allocates (pymalloc) instead of a pure loop")
    ap.add_argument("--max-delay-ms", type=float, default=20.0)
    ap.add_argument("--hang-s", type=float, default=3.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--diagnose", metavar="DIR", help="gdb stacks of hung runs into DIR")
    args = ap.parse_args(argv)
    if args.serve:
        return _serve(args)
    res = run(args.kills, gil_repair=bool(args.gil_repair),
              condvar_repair=bool(args.condvar_repair), alloc=args.alloc,
              seed=args.seed, hang_s=args.hang_s, max_delay_ms=args.max_delay_ms,
              diagnose_dir=args.diagnose)
    print(json.dumps(res.__dict__, default=dict) if args.json else res.line())
    for note in res.notes[:20]:
        print("  ", note)
    return 0


if __name__ == "__main__":
    sys.exit(main())
