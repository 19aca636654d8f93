"""cffi (API mode) builder for faults._gilfault (gilfault.c: die inside the GIL)."""
from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent

ffibuilder = FFI()
ffibuilder.cdef("""
    #define GILFAULT_DROP_GIL_LOCKED ...
    #define GILFAULT_TAKE_GIL_HANDOVER ...
    #define GILFAULT_TAKE_GIL_CHECKING ...
    #define GILFAULT_SWITCH_MUTEX ...
    #define GILFAULT_DROP_GIL_SIGNALLING ...
    int gilfault_die_in_gil(int where);
""")
ffibuilder.set_source(
    "cloneguard.faults._gilfault",
    '#include "gilfault.c"\n',
    include_dirs=[str(HERE)],
    depends=[str(HERE / n) for n in ("gilfault.c", "gilfault.h")],
    libraries=["pthread"],
    extra_compile_args=["-std=gnu11", "-Wall"],
    # CPython internals: not the limited API.
    define_macros=[("_CFFI_NO_LIMITED_API", None)],
    py_limited_api=False,
)
