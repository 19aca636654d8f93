"""What lies at an address of the container's memory, in words: which
library's data (and the symbol there, when the library's symbol table has
one), or which kind of anonymous memory.

Read from /proc/self/maps and the library file's ELF symbol tables, never
with dladdr: that takes the loader's lock, which a dead node may hold (the
lock doctor reports exactly such locks).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from functools import lru_cache


@dataclass(frozen=True)
class Mapping:
    start: int
    end: int
    perms: str
    offset: int
    path: str  # "" for anonymous memory, "[heap]", "[stack]", or a file


def mappings() -> list[Mapping]:
    out = []
    with open("/proc/self/maps") as f:
        for line in f:
            parts = line.split(maxsplit=5)
            lo, hi = parts[0].split("-")
            out.append(
                Mapping(
                    int(lo, 16), int(hi, 16), parts[1], int(parts[2], 16), parts[5].strip() if len(parts) > 5 else ""
                )
            )
    return out


def describe(addr: int) -> str:
    """E.g. "libnativelock.so's data (lock_a+0)", "anonymous memory (a heap
    or a thread's stack)", or "unmapped memory"."""
    maps = mappings()
    i = next((k for k, m in enumerate(maps) if m.start <= addr < m.end), None)
    if i is None:
        return "unmapped memory"
    m = maps[i]
    path = m.path
    if not path and i > 0 and maps[i - 1].end == m.start and maps[i - 1].path.startswith("/"):
        path = maps[i - 1].path  # a library's .bss follows its file mapping
    if path.startswith("/"):
        base = next((x.start for x in maps if x.path == path and x.offset == 0), None)
        name = os.path.basename(path)
        sym = _symbol(path, addr - base) if base is not None else None
        return f"{name}'s data ({sym})" if sym else f"{name}'s data (+{addr - (base or m.start):#x})"
    if path == "[heap]":
        return "the container's brk heap"
    if path.startswith("[stack"):
        return "the container's main stack"
    return "anonymous memory (a heap or a thread's stack)"


def _symbol(path: str, vaddr: int) -> str | None:
    """ "name+off" of the data symbol holding vaddr (relative to the load
    base), from .symtab or .dynsym."""
    for value, size, name in _data_symbols(path):
        if value <= vaddr < value + max(size, 1):
            return f"{name}+{vaddr - value}"
    return None


@lru_cache(maxsize=64)
def _data_symbols(path: str) -> tuple[tuple[int, int, str], ...]:
    """(value, size, name) of every STT_OBJECT symbol in an ELF64 LE file,
    minus the first PT_LOAD's vaddr (so values are offsets from the base)."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError:
        return ()
    if data[:4] != b"\x7fELF" or data[4] != 2 or data[5] != 1:
        return ()
    phoff, shoff = struct.unpack_from("<QQ", data, 0x20)
    phentsize, phnum, shentsize, shnum = struct.unpack_from("<HHHH", data, 0x36)
    first_load = 0
    for k in range(phnum):
        p_type, _, _, p_vaddr = struct.unpack_from("<IIQQ", data, phoff + k * phentsize)
        if p_type == 1:  # PT_LOAD
            first_load = p_vaddr
            break
    sections = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + k * shentsize) for k in range(shnum)]
    out = []
    for sh in sections:
        sh_type, sh_offset, sh_size, sh_link, sh_entsize = sh[1], sh[4], sh[5], sh[6], sh[9]
        if sh_type not in (2, 11) or not sh_entsize:  # SHT_SYMTAB, SHT_DYNSYM
            continue
        strtab = sections[sh_link]
        str_off = strtab[4]
        for k in range(sh_size // sh_entsize):
            st_name, st_info, _, st_shndx, st_value, st_size = struct.unpack_from(
                "<IBBHQQ", data, sh_offset + k * sh_entsize
            )
            if st_info & 0xF != 1 or st_shndx == 0:  # STT_OBJECT, defined
                continue
            end = data.index(b"\0", str_off + st_name)
            out.append((st_value - first_load, st_size, data[str_off + st_name : end].decode(errors="replace")))
    return tuple(sorted(set(out)))
