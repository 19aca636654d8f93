"""``--core-dumps DIR``: the dump of a node process that caught a fatal
signal, written by gdb's ``gcore`` while its crashing task waits in its
crash handler (crash.c), named after the node: ``DIR/core.<node>.<pid>``.

Why gdb and not the kernel: node processes run with core dumps off
(RLIMIT_CORE, child.c), and the kernel's dump would go where the machine's
``core_pattern`` says, under a name that cannot say which node it was. A
dump holds the whole shared address space: every node's memory and the
container's, so it is as large as the container and as private.

Size: gdb writes every readable page, touched or not, so while one is
written the allocator guard's reserved and never-used address space is
left out (MADV_DONTDUMP), and afterwards its runs of zeros (thread stacks
never grown into, ...) are made holes (``fallocate --dig-holes``): the file's
apparent size is what was mapped (GiBs), what it takes on disk is about the
memory in use (tens of MiB for a small composition).

What stays as it was: a fault on a thread the node created writes its
crash report but no dump (only the node's main task, which runs its
executor, waits for one); a death by SIGKILL writes neither; and a fault
on a task that holds the GIL gets no dump (CRASHED says "no core dump: it
held the GIL"): the dump is this module's, in the container's Python, which
would wait for that GIL while the task waited for its dump. The dump path
takes no lock a node process may hold until the task is let go, but the
core's event listener does take the core's own lock first; writing the dump
from a C thread of the monitor, with no Python at all, is the way to close
that too.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

#: How long gdb may take over one dump (the crashing task waits CG_CORE_WAIT_S).
GCORE_TIMEOUT_S = 300


def unavailable(directory: Path) -> str | None:
    """Why dumps cannot be written into ``directory`` here, or None."""
    if shutil.which("gdb") is None:
        return "it needs gdb, which writes the dumps (apt install gdb)"
    if directory.exists() and not directory.is_dir():
        return f"{directory} is not a directory"
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot make {directory}: {exc.strerror}"
    return None


def path_for(directory: Path, full_name: str, pid: int) -> Path:
    """``core.<node>.<pid>``, the node's full name with its slashes as dots."""
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", full_name.strip("/").replace("/", ".")) or "node"
    return directory / f"core.{name}.{pid}"


def write(path: Path, pid: int) -> str | None:
    """Dump process ``pid`` into ``path`` with gdb; None, or why not."""
    cmd = ["gdb", "-nx", "-batch", "-p", str(pid), "-ex", f"gcore {path}"]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=GCORE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return f"gdb took over {GCORE_TIMEOUT_S} s"
    if not path.exists():
        tail = (out.stderr or out.stdout).strip().splitlines()[-1:] or [f"exit status {out.returncode}"]
        return f"gdb wrote none: {tail[0]}"
    if shutil.which("fallocate"):  # util-linux; without it the file stays whole
        subprocess.run(["fallocate", "--dig-holes", str(path)], capture_output=True, timeout=GCORE_TIMEOUT_S)
    return None
