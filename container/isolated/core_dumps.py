"""``--core-dumps DIR``: the dump of a node process that caught a fatal
signal, named after the node: ``DIR/core.<node>.<pid>``. This module checks
the setting and names the files; the clone core's monitor writes them
(dumps.c): gdb's ``gcore`` while the crashing task waits in its crash
handler, then ``fallocate --dig-holes``, with no Python involved, so a task
that crashed holding the GIL or any lock is dumped all the same.

Why gdb and not the kernel: node processes run with core dumps off
(RLIMIT_CORE, child.c), and the kernel's dump would go where the machine's
``core_pattern`` says, under a name that cannot say which node it was. A
dump holds the whole shared address space: every node's memory and the
container's, so it is as large as the container and as private.

Size: gdb writes every readable page, touched or not, so while one is
written the allocator guard's reserved and never-used address space is
left out (MADV_DONTDUMP), and afterwards its runs of zeros (thread stacks
never grown into, ...) are made holes: the file's apparent size is what was
mapped (GiBs), what it takes on disk is about the memory in use (tens of
MiB for a small composition).

What gets none: a fault on a thread the node created writes its crash
report but no dump (only the node's main task, which runs its executor,
waits for one), and a death by SIGKILL writes neither. While a task that
holds the GIL waits for its dump, the container's Python waits with it
(seconds); the other node processes' native threads, DDS's among them, go on.
"""

from __future__ import annotations

import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from cloneguard.container.isolated._clonecore import lib

#: A dump's path must fit the core's buffer with the longest name path_for makes.
_NAME_MAX = 120


@dataclass(frozen=True)
class Tools:
    """The programs the monitor runs, by absolute path."""

    gdb: str
    fallocate: str  # "": none (the dump keeps its runs of zeros)


def unavailable(directory: Path) -> str | None:
    """Why dumps cannot be written into ``directory`` here, or None."""
    if shutil.which("gdb") is None:
        return "it needs gdb, which writes the dumps (apt install gdb)"
    if directory.exists() and not directory.is_dir():
        return f"{directory} is not a directory"
    if len(str(directory.resolve()).encode()) + _NAME_MAX + 20 >= lib.CG_CORE_PATH:
        return f"its path is too long (a dump's path must stay under {lib.CG_CORE_PATH} bytes)"
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"cannot make {directory}: {exc.strerror}"
    return None


def tools() -> Tools:
    """Where gdb and fallocate are (unavailable() said gdb is there)."""
    found = {name: shutil.which(name) or "" for name in ("gdb", "fallocate")}
    for name, path in found.items():
        if len(path.encode()) >= lib.CG_TOOL_PATH:
            raise ValueError(f"{name}'s path is too long: {path}")
    return Tools(str(Path(found["gdb"]).resolve()), found["fallocate"] and str(Path(found["fallocate"]).resolve()))


def size(path: str) -> str:
    """What a written dump takes, for the log: on disk and in address space.
    Never raises (the crash path logs it; the file may be gone already)."""
    try:
        st = Path(path).stat()
    except OSError as exc:
        return f"now unreadable: {exc.strerror}"
    return f"{st.st_blocks * 512 >> 20} MiB on disk, {st.st_size >> 20} MiB of address space"


def path_for(directory: Path, name: str, pid: int) -> Path:
    """``core.<name>.<pid>``: a node's full name with its slashes as dots
    (what is not a letter, digit, ``_``, ``.`` or ``-`` becomes ``_``)."""
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", name.strip("/").replace("/", "."))[:_NAME_MAX] or "node"
    return directory / f"core.{name}.{pid}"
