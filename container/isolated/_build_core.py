"""cffi (API mode) builder for container.isolated._clonecore.

The C lives in clonecore/, one job per file (core.h lists them): the
generated module includes core.h, the declarations Python's calls need, and
links the core's files as further sources; gilrepair.c is among them,
compiled with Py_BUILD_CORE (it reads CPython's internal GIL state; see
there), sharing only repair.h with the rest.  The cdef is made from the
headers' cdef blocks (scripts/cdef.py): what Python sees is written once, in C.
Built with -fvisibility=hidden: the module exports its PyInit function only.

Built by setup.py (``cffi_modules``); after an edit of the C,
``pip install --no-build-isolation --no-deps -e .`` rebuilds it in place.
"""

import runpy
from pathlib import Path

from cffi import FFI

# The project's C warning flags: one list for every build (scripts/cflags.py).
CFLAGS = runpy.run_path(str(Path(__file__).resolve().parents[2] / "scripts" / "cflags.py"))
WARNINGS = CFLAGS["WARNINGS"]

HERE = Path(__file__).resolve().parent
SOURCES = (
    "clonecore.c",
    "monitor.c",
    "child.c",
    "crash.c",
    "dumps.c",
    "contexts.c",
    "probes.c",
    "gilrepair.c",
    "interp.c",
    "mutexes.c",
    "listenerwait.c",
    "pkeys.c",
    "herald.c",
    "deathtext.c",
    "lastresort.c",
    "memwatch.c",
    "heldscan.c",
    "sigsafe.c",
)

# What Python's calls need, each written once, in the C headers' cdef
# blocks (scripts/cdef.py says how they become the cdef).
CORE = HERE / "clonecore"  # the clone core's C; the allocator guard's API is in allocguard/
# The headers whose cdef blocks Python sees, in order: the shapes (the
# guard's, the repairs', the core's), then what each file offers.
OFFERS = ("clonecore", "child", "crash", "contexts", "deathtext", "herald", "lastresort", "listenerwait", "probes",
          "pkeys", "memwatch", "dumps", "monitor")  # fmt: skip
HEADERS = (
    HERE / "allocguard" / "allocguard.h",
    CORE / "repair.h",
    CORE / "core.h",
    *(CORE / f"{name}.h" for name in OFFERS),
)
CDEF = runpy.run_path(str(HERE.parents[1] / "scripts" / "cdef.py"))["cdef"](HEADERS)

ffibuilder = FFI()
ffibuilder.cdef(CDEF)
ffibuilder.set_source(
    "cloneguard.container.isolated._clonecore",
    "".join(f'#include "{h.name}"\n' for h in HEADERS[2:])
    + CFLAGS["cffi_init_prototype"]("cloneguard.container.isolated._clonecore"),
    # setuptools wants sources relative to the repo root (where setup.py runs).
    sources=[f"container/isolated/clonecore/{n}" for n in SOURCES],
    include_dirs=[str(CORE)],
    depends=[
        *(f"container/isolated/clonecore/{h.name}" for h in HEADERS[1:]),
        "container/isolated/clonecore/sigsafe.h",
        "container/isolated/allocguard/allocguard.h",
        "scripts/cdef.py",
    ],
    libraries=["dl", "pthread"],
    extra_compile_args=["-std=gnu11", *WARNINGS, "-Wno-unused-function", "-fvisibility=hidden"],
    # The C uses the non-limited C API (PyThreadState fields): cffi would
    # otherwise define Py_LIMITED_API (the macro covers ffibuilder.compile(),
    # the keyword a setuptools build).
    define_macros=[("_CFFI_NO_LIMITED_API", None)],
    py_limited_api=False,
)
