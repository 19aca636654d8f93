"""cffi (API mode) builder for faults._hammer (the malloc hammer, hammer.c)."""

import runpy
from pathlib import Path

from cffi import FFI

# The project's C warning flags: one list for every build (scripts/cflags.py).
CFLAGS = runpy.run_path(str(Path(__file__).resolve().parents[1] / "scripts" / "cflags.py"))
WARNINGS = CFLAGS["WARNINGS"]

HERE = Path(__file__).resolve().parent
header_cdef = runpy.run_path(str(HERE / "_cffi_fault.py"))["header_cdef"]

ffibuilder = FFI()
ffibuilder.cdef(header_cdef("hammer"))
ffibuilder.set_source(
    "cloneguard.faults._hammer",
    '#include "hammer.c"\n' + CFLAGS["cffi_init_prototype"]("cloneguard.faults._hammer"),
    include_dirs=[str(HERE)],
    depends=[str(HERE / "hammer.c"), str(HERE / "hammer.h")],
    extra_compile_args=["-O2", "-std=gnu11", *WARNINGS],
)
