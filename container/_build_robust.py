"""cffi (API mode) builder for container._robust (robust.c: robust mutexes)."""

import runpy
from pathlib import Path

from cffi import FFI

# The project's C warning flags: one list for every build (scripts/cflags.py).
CFLAGS = runpy.run_path(str(Path(__file__).resolve().parents[1] / "scripts" / "cflags.py"))
WARNINGS = CFLAGS["WARNINGS"]

HERE = Path(__file__).resolve().parent

ffibuilder = FFI()
# robust.h's declarations, less its preprocessor lines; pthread_mutex_t is
# opaque to Python.
ffibuilder.cdef(
    "typedef struct { ...; } pthread_mutex_t;\n"
    + "".join(line for line in (HERE / "robust.h").open() if not line.startswith("#"))
)
ffibuilder.set_source(
    "cloneguard.container._robust",
    '#include "robust.c"\n' + CFLAGS["cffi_init_prototype"]("cloneguard.container._robust"),
    include_dirs=[str(HERE)],
    depends=[str(HERE / "robust.c"), str(HERE / "robust.h")],
    libraries=["pthread"],
    extra_compile_args=["-std=gnu11", *WARNINGS],
)
