"""What the cffi builders of the rig's C fault points share (gilfault,
interpfault, nativelock): ``<name>.c`` compiled as a unit of its own beside
``<name>.h``, into ``cloneguard.faults._<name>``, with the project's warning
flags. Each builder loads this file with runpy (cffi runs builders as
scripts) and exposes the ``ffibuilder`` it returns."""

import runpy
from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent
# The project's C warning flags: one list for every build (scripts/cflags.py).
CFLAGS = runpy.run_path(str(HERE.parent / "scripts" / "cflags.py"))
WARNINGS = CFLAGS["WARNINGS"]


def header_cdef(name: str) -> str:
    """``<name>.h``'s declarations, less its preprocessor lines."""
    return "".join(line for line in (HERE / f"{name}.h").open() if not line.startswith("#"))


def fault_builder(name: str, cdef: str, *, cpython_internals: bool = False, libraries=()) -> FFI:
    """``cpython_internals``: the C reads CPython's internal state
    (Py_BUILD_CORE in its own unit), so not the limited API."""
    ffibuilder = FFI()
    ffibuilder.cdef(cdef)
    internals = {"define_macros": [("_CFFI_NO_LIMITED_API", None)], "py_limited_api": False}
    ffibuilder.set_source(
        f"cloneguard.faults._{name}",
        f'#include "{name}.h"\n' + CFLAGS["cffi_init_prototype"](f"cloneguard.faults._{name}"),
        sources=[f"../faults/{name}.c"],  # relative to rig/, where setup.py runs
        include_dirs=[str(HERE)],
        depends=[str(HERE / f"{name}.{ext}") for ext in ("c", "h")],
        libraries=list(libraries),
        extra_compile_args=["-std=gnu11", *WARNINGS],
        **(internals if cpython_internals else {}),
    )
    return ffibuilder
