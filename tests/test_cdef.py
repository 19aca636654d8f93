"""The core's cdef is made from its C headers' cdef blocks
(scripts/cdef.py): each rule, and what it refuses."""

from __future__ import annotations

import re
import runpy
from pathlib import Path

import pytest

from cloneguard.container.isolated import _clonecore

REPO = Path(__file__).resolve().parents[1]
CDEF = runpy.run_path(str(REPO / "scripts" / "cdef.py"))
#: The headers the core's module is built from, as its builder names them.
CORE_HEADERS = runpy.run_path(str(REPO / "container" / "isolated" / "_build_core.py"))["HEADERS"]

HEADER = """
#include <stdint.h>
int not_seen(void);
/* cdef: begin */
/* cdef: const SEGV_PKUERR */
#define SIZE 16 /* a size */
#define MASK ((uint32_t)1 << SIZE)
#define MAKE_REQUEST(a, b) ((a) | (b))
enum { FIRST = 1, SECOND, THIRD = FIRST << 2 };
#define LIST(X) \\
    X(ALPHA, 0) \\
    X(BETA, 1)
enum {
#define BIT(name, bit) FLAG_##name = 1 << (bit),
    LIST(BIT)
#undef BIT
};
struct shown {
    int a;               /* kept */
    char name[SIZE];     /* the compiler's length */
    long fixed[3];
    /* cdef: the rest is the core's */
    void *hidden;
    struct other *more;
};
int shown_call(struct shown *s);
/* cdef: end */
int not_seen_either(void);
"""


def test_a_blocks_declarations_become_the_cdef(tmp_path):
    header = tmp_path / "sample.h"
    header.write_text(HEADER)
    text = CDEF["cdef"]([header])
    consts = {line.split()[1] for line in text.splitlines() if line.startswith("#define")}
    assert consts == {"SEGV_PKUERR", "SIZE", "MASK", "FIRST", "SECOND", "THIRD", "FLAG_ALPHA", "FLAG_BETA"}
    assert all(line.endswith(" ...") for line in text.splitlines() if line.startswith("#define"))
    assert "char name[...];" in text and "long fixed[3];" in text
    assert "...;" in text and "hidden" not in text and "more" not in text
    assert "int shown_call(struct shown *s);" in text
    assert "not_seen" not in text and "MAKE_REQUEST" not in text and "LIST" not in text


@pytest.mark.parametrize(
    ("block", "says"),
    [
        ("/* cdef: begin */\n#if 1\nint f(void);\n#endif\n/* cdef: end */", "only #define and #undef"),
        ("/* cdef: begin */\nint f(void);\n", "not closed"),
        ("/* cdef: begin */\nenum { L(M) };\n/* cdef: end */", "needs its list and its maker"),
    ],
)
def test_what_a_block_may_not_hold_is_refused(tmp_path, block, says):
    header = tmp_path / "bad.h"
    header.write_text(block)
    with pytest.raises(CDEF["CdefError"], match=says):
        CDEF["cdef"]([header])


def test_the_core_was_built_from_its_headers_blocks():
    """Every constant and function the blocks declare is the module's: the
    module in the tree was built from the headers as they are (cffi
    compiles each declaration against them)."""
    text = CDEF["cdef"](CORE_HEADERS)
    names = {line.split()[1] for line in text.splitlines() if line.startswith("#define")}
    names |= set(re.findall(r"(\w+)\([^;]*?\);", text, re.S))
    assert names <= set(dir(_clonecore.lib)), sorted(names - set(dir(_clonecore.lib)))
    assert {"cg_start", "cg_spawn", "CG_REPAIR_PY_OBJECTS", "SEGV_PKUERR", "CGA_QUARANTINED"} <= names
