"""The cgroup janitor: removes a container's cgroups once the container is gone.

    python -I -S cgroup_janitor.py <container pid> <cgroup2 root> [<v1 cpu root>]

NodeCgroups starts it with its stdin the read end of a pipe whose write end
only the container holds (the node processes share the container's fd
table, and the end is close-on-exec). End of file on stdin means the
container and every node process have ended, however the container ended:
SIGKILL, the watchdog's exit, a crash. A container that stopped normally
removed its cgroups itself and there is nothing left to do. Otherwise the
janitor kills what is still in a node's cgroup (``cgroup.kill``; only that
container's node processes are ever put there), waits until each is empty,
and removes the trees.

It runs in a session of its own and ignores SIGINT, SIGTERM and SIGHUP, so
that stopping the container's process group does not stop it first; and it
is not the container's child (it forks once and the first process exits), so
that what counts the container's children counts its node processes only.
It uses the standard library only and starts without site: it needs none
of the container's imports.
"""

from __future__ import annotations

import errno
import os
import signal
import sys
import time

EMPTY_TIMEOUT_S = 5.0


def _wait_empty(node_dir: str) -> bool:
    """Until the kernel says no task is left in the cgroup (bounded)."""
    deadline = time.monotonic() + EMPTY_TIMEOUT_S
    while True:
        try:
            with open(os.path.join(node_dir, "cgroup.events")) as f:
                if "populated 0" in f.read().splitlines():
                    return True
        except FileNotFoundError:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)


def _rmdir(path: str, problems: list[str]) -> None:
    deadline = time.monotonic() + EMPTY_TIMEOUT_S
    while True:
        try:
            os.rmdir(path)
            return
        except FileNotFoundError:
            return
        except OSError as exc:
            if exc.errno != errno.EBUSY or time.monotonic() >= deadline:
                problems.append(f"{path}: {exc.strerror}")
                return
            time.sleep(0.01)


def clean(roots: list[str]) -> tuple[list[str], list[str]]:
    """Empty and remove every ``node-*`` cgroup under ``roots``, then the
    roots. Returns (what was removed, what could not be)."""
    removed: list[str] = []
    problems: list[str] = []
    present = [r for r in roots if os.path.isdir(r)]
    nodes = {r: sorted(os.path.join(r, d) for d in os.listdir(r) if d.startswith("node-")) for r in present}
    for root in present:
        for node_dir in nodes[root]:
            kill = os.path.join(node_dir, "cgroup.kill")  # cgroup2 only
            if os.path.exists(kill):
                try:
                    with open(kill, "w") as f:
                        f.write("1")
                except OSError as exc:
                    problems.append(f"{kill}: {exc.strerror}")
                if not _wait_empty(node_dir):
                    problems.append(f"{node_dir}: processes still in it after {EMPTY_TIMEOUT_S:g} s")
    for root in present:
        for path in nodes[root] + [root]:
            _rmdir(path, problems)
            if not os.path.exists(path):
                removed.append(path)
    return removed, problems


def main(argv: list[str]) -> int:
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    if os.fork() > 0:
        os._exit(0)  # the container reaps this one at once
    container_pid, roots = argv[1], argv[2:]
    while os.read(0, 4096):  # nothing is ever written: wait for end of file
        pass
    removed, problems = clean(roots)
    if removed or problems:
        print(
            f"cloneguard cgroup janitor: the container (pid {container_pid}) ended without "
            f"removing its cgroups; removed {removed}" + (f"; could not remove: {problems}" if problems else ""),
            file=sys.stderr,
            flush=True,
        )
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
