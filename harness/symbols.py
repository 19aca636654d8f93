"""Native frames as a crash report writes them, with function names added.

glibc's ``backtrace_symbols_fd`` names a frame only by a dynamic symbol:
one inside a library's static function reads ``libc.so.6(+0x85f16)``, or
``libpython3.11.so.1.0(_PyEval_EvalFrameDefault+0x1b2c)`` when the nearest
exported symbol is not the function at all. Where the library has symbols
(a symbol table, or debug information), ``addr2line`` names the function
(and its file and line) from the library's own file, after the process is
gone: one ``addr2line`` run per library.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess

# "/path/lib.so(sym+0x1f)[0x7f...]" or "/path/lib.so(+0x1f)[0x7f...]"
_FRAME = re.compile(r"^(?P<lib>/[^\s()]+)\((?P<sym>[^)+]*)\+(?P<off>0x[0-9a-f]+)\)\s*\[(?P<pc>0x[0-9a-f]+)\]\s*$")
ADDR2LINE_TIMEOUT_S = 30


def available() -> bool:
    return shutil.which("addr2line") is not None


def _file_offset(lib: str, sym: str, off: int) -> int | None:
    """The offset into ``lib`` of a frame: given relative to the library
    (no symbol), or to a dynamic symbol whose offset ``nm -D`` knows."""
    if not sym:
        return off
    try:
        out = subprocess.run(
            ["nm", "-D", "--defined-only", lib], capture_output=True, text=True, timeout=ADDR2LINE_TIMEOUT_S
        ).stdout
    except (OSError, subprocess.TimeoutExpired):
        return None
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[2].split("@")[0] == sym:
            return int(parts[0], 16) + off
    return None


def symbolize(text: str) -> str:
    """``text`` with each native frame line followed by `` = function
    (file:line)`` where addr2line can tell, unchanged where it cannot."""
    lines = text.splitlines()
    if not available():
        return text
    wanted: dict[str, list[tuple[int, int]]] = {}  # lib -> [(line index, file offset)]
    for i, line in enumerate(lines):
        m = _FRAME.match(line.strip())
        if not m or not os.path.exists(m["lib"]):
            continue
        where = _file_offset(m["lib"], m["sym"], int(m["off"], 16))
        if where is not None:
            # a return address: the call is the instruction before it
            wanted.setdefault(m["lib"], []).append((i, max(where - 1, 0)))
    for lib, frames in wanted.items():
        try:
            out = subprocess.run(
                ["addr2line", "-f", "-C", "-e", lib, *(hex(off) for _, off in frames)],
                capture_output=True,
                text=True,
                timeout=ADDR2LINE_TIMEOUT_S,
            ).stdout.splitlines()
        except (OSError, subprocess.TimeoutExpired):
            continue
        for n, (i, _) in enumerate(frames):
            func, place = (out[2 * n], out[2 * n + 1]) if 2 * n + 1 < len(out) else ("??", "??:0")
            if func != "??":
                at = "" if place.startswith("??") else f" ({place.split(' ')[0]})"
                lines[i] += f" = {func}{at}"
    return "\n".join(lines) + ("\n" if text.endswith("\n") else "")
