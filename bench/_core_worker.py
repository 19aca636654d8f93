"""Measurements that need a CloneCore of their own, in a fresh process.

Only one CloneCore may be open per process, and the benchmark process itself
runs rclpy clients, so these run here, started by the benchmarks:

    python -m cloneguard.bench._core_worker spawn --n 50     # clone3 vs fork+exec vs fork
    python -m cloneguard.bench._core_worker kill --n 50      # outside signal -> monitor

It prints one JSON object (lists of nanoseconds) on stdout. rclpy is
imported first so the process has the heap and mappings of a container.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time

import rclpy  # noqa: F401  (a container-sized process: see the docstring)

from cloneguard.container.isolated.core import CloneCore

STAMP = "import os,time;os.write(1,b'%d'%time.monotonic_ns())"
NR_CLOCK_NANOSLEEP = 230  # what time.sleep blocks in (x86_64)


def _exec_stamp(argv: list[str]) -> tuple[int, int]:
    """fork+exec ``argv`` (subprocess, as a launcher would); (t0, the child's first-line stamp)."""
    t0 = time.monotonic_ns()
    p = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE)
    assert p.stdout is not None  # stdout=PIPE
    out = p.stdout.read()
    p.stdout.close()
    p.wait()
    return t0, int(out)


def _fork_stamp() -> tuple[int, int]:
    r, w = os.pipe()
    t0 = time.monotonic_ns()
    pid = os.fork()
    if pid == 0:
        os.write(w, b"%d" % time.monotonic_ns())
        os._exit(0)
    os.close(w)
    out = os.read(r, 64)
    os.close(r)
    os.waitpid(pid, 0)
    return t0, int(out)


def spawn(n: int) -> dict:
    out: dict[str, list[int]] = {
        k: []
        for k in (
            "clone_first_line",
            "clone_spawn_returned",
            "clone_cloned",
            "forkexec_site",
            "forkexec_nosite",
            "fork_first_line",
            "clone_hot_first_line",
        )
    }
    stamps: list[int] = []

    def target() -> None:
        stamps.append(time.monotonic_ns())

    core = CloneCore()
    try:
        for _ in range(n):  # interleaved, so drift on a noisy host hits all alike
            t0 = time.monotonic_ns()
            child = core.spawn(target)
            t1 = time.monotonic_ns()
            death = core.wait(child, 10)
            if death is None:
                raise RuntimeError(f"clone child {child.pid} not reaped within 10 s")
            core.release(child)
            out["clone_first_line"].append(stamps[-1] - t0)
            out["clone_spawn_returned"].append(t1 - t0)
            out["clone_cloned"].append(child.start_time_ns - t0)  # the monitor, just before clone3
            t0, t = _exec_stamp([sys.executable, "-c", STAMP])
            out["forkexec_site"].append(t - t0)
            t0, t = _exec_stamp([sys.executable, "-I", "-S", "-c", STAMP])
            out["forkexec_nosite"].append(t - t0)
        for _ in range(n):  # and back to back, nothing in between (a best case)
            t0 = time.monotonic_ns()
            child = core.spawn(target)
            if core.wait(child, 10) is None:
                raise RuntimeError(f"clone child {child.pid} not reaped within 10 s")
            core.release(child)
            out["clone_hot_first_line"].append(stamps[-1] - t0)
        # Last: a bare fork marks every page of this process copy-on-write,
        # and the writes after it fault them in again one by one (the next
        # clone spawn took 0.44 ms instead of 0.24, median of 60, one run), so it must
        # not run between the others. subprocess (fork+exec) uses vfork here.
        for _ in range(n):
            t0, t = _fork_stamp()
            out["fork_first_line"].append(t - t0)
    finally:
        core.close()
    return out


def _blocked_in_sleep(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/syscall") as f:
            return f.read().split()[0] == str(NR_CLOCK_NANOSLEEP)
    except (OSError, IndexError):
        return False


def kill(n: int) -> dict:
    """An idle child (in time.sleep) killed from outside: os.kill -> the
    monitor's detection stamp, and -> on_event in Python."""
    arrived: dict[int, int] = {}
    cond = threading.Condition()

    def on_event(event) -> None:
        now = time.monotonic_ns()
        with cond:
            arrived.setdefault(event.serial, now)
            cond.notify_all()

    out = {}
    core = CloneCore(on_event=on_event)
    try:
        for sig in (signal.SIGKILL, signal.SIGSEGV):
            detect, deliver = [], []
            for _ in range(n):
                child = core.spawn(lambda: time.sleep(60))
                deadline = time.monotonic() + 10
                while not _blocked_in_sleep(child.pid):
                    if time.monotonic() > deadline:
                        raise RuntimeError(f"child {child.pid} never got to time.sleep")
                    time.sleep(0.0005)
                t0 = time.monotonic_ns()
                os.kill(child.pid, sig)
                death = core.wait(child, 10)
                if death is None:
                    raise RuntimeError(f"child {child.pid} not reaped within 10 s of {sig.name}")

                def came(serial: int = child.serial) -> bool:
                    return serial in arrived

                with cond:
                    if not cond.wait_for(came, 10):
                        raise RuntimeError(f"no on_event for child {child.pid} within 10 s")
                detect.append(death.detected_monotonic_ns - t0)
                deliver.append(arrived[child.serial] - t0)
                core.release(child)
            out[f"{sig.name}_monitor"] = detect
            out[f"{sig.name}_on_event"] = deliver
    finally:
        core.close()
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m cloneguard.bench._core_worker")
    parser.add_argument("what", choices=("spawn", "kill"))
    parser.add_argument("--n", type=int, default=50)
    opts = parser.parse_args(argv)
    result = spawn(opts.n) if opts.what == "spawn" else kill(opts.n)
    sys.stdout.write(json.dumps(result) + "\n")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
