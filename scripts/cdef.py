"""A cffi module's cdef, made from its C headers (the clone core's, rclglue's):
each declaration Python's calls need is written once, in C, between
``/* cdef: begin */`` and ``/* cdef: end */``; this turns those blocks into
what cffi's cdef parses.

In a block:

* ``#define NAME value`` (any value): the constant, its value the C
  compiler's (``#define NAME ...``); a function-like macro is left out,
  unless it lists entries for an enum (below);
* ``enum { A = ..., B, ... };``: each enumerator, as a constant;
* ``#define LIST(X) X(NAME, ...) X(NAME, ...) ...`` and, further on,
  ``#define MAKE(name, ...) PREFIX##name ...`` and ``enum { LIST(MAKE) };``:
  PREFIX + each NAME, as a constant (an X-macro list, repair.h's);
* ``/* cdef: const NAME */``: a constant of a system header (SEGV_PKUERR);
* a struct: as it is, but an array's length that is not a number becomes
  ``...`` (the compiler's), and ``/* cdef: the rest is the core's */``
  ends what Python sees of it (``...;``: the compiler lays out the rest);
* prototypes: as they are.

``#undef`` is passed over; anything else of the preprocessor in a block is an error, as is a block
left open. cffi strips the comments left."""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

BEGIN, END = "/* cdef: begin */", "/* cdef: end */"
REST = "/* cdef: the rest is the core's */"
_CONST = re.compile(r"/\* cdef: const (\w+) \*/")
_COMMENT = re.compile(r"/\*.*?\*/|//[^\n]*", re.S)
_DEFINE = re.compile(r"#define\s+(\w+)(\([^)]*\))?\s*(.*)", re.S)
_ENUM = re.compile(r"\benum\s*\w*\s*\{(.*?)\}\s*;", re.S)
_ARRAY = re.compile(r"\[\s*([^\]]*?)\s*\]")


class CdefError(ValueError):
    pass


def blocks(text: str, where: str) -> list[str]:
    """The text of each marked block of a header."""
    out, at = [], 0
    while (start := text.find(BEGIN, at)) >= 0:
        end = text.find(END, start)
        if end < 0:
            raise CdefError(f"{where}: a cdef block is not closed")
        out.append(text[start + len(BEGIN) : end])
        at = end + len(END)
    return out


def _struct_rest(text: str) -> str:
    """Each REST marker, and the fields after it up to its struct's end, as
    ``...;``."""
    while (at := text.find(REST)) >= 0:
        end = text.find("};", at)
        if end < 0:
            raise CdefError("the rest of a struct is marked, but the struct does not end")
        text = text[:at] + "...;\n" + text[end:]
    return text


def translate(block: str, where: str) -> str:
    """One block, as cdef text."""
    consts = _CONST.findall(block)
    block = _struct_rest(_CONST.sub("", block))
    block = _COMMENT.sub(" ", block).replace("\\\n", " ")
    lists: dict[str, list[str]] = {}
    makers: dict[str, str] = {}
    statements = []
    for line in block.split("\n"):
        if not line.lstrip().startswith("#"):
            statements.append(line)
            continue
        if line.strip().startswith("#undef"):
            continue
        found = _DEFINE.match(line.strip())
        if found is None:
            raise CdefError(f"{where}: only #define and #undef may be in a cdef block: {line.strip()!r}")
        name, params, body = found.groups()
        if params is None:
            consts.append(name)
        elif params.replace(" ", "") == "(X)":
            lists[name] = re.findall(r"\bX\(\s*(\w+)", body)
        elif prefix := re.match(r"(\w+?)##", body.strip()):
            makers[name] = prefix[1]
    rest = "\n".join(statements)
    for enum in _ENUM.finditer(rest):
        for item in (i.strip() for i in enum[1].split(",")):
            if used := re.fullmatch(r"(\w+)\((\w+)\)", item):
                listed, maker = used.groups()
                if listed not in lists or maker not in makers:
                    raise CdefError(f"{where}: {item} needs its list and its maker in the block")
                consts += [makers[maker] + entry for entry in lists[listed]]
            elif enumerator := re.match(r"\w+", item):
                consts.append(enumerator[0])
    rest = _ENUM.sub("", rest)
    rest = _ARRAY.sub(lambda m: m[0] if m[1].isdigit() else "[...]", rest)
    return "".join(f"#define {name} ...\n" for name in consts) + rest


def cdef(headers: Iterable[Path]) -> str:
    """The blocks of these headers, in order, as one cdef."""
    return "\n".join(translate(b, h.name) for h in headers for b in blocks(h.read_text(), h.name))
