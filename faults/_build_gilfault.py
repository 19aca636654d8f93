"""cffi (API mode) builder for faults._gilfault (gilfault.c: die inside the GIL)."""

import runpy
from pathlib import Path

fault_builder = runpy.run_path(str(Path(__file__).with_name("_cffi_fault.py")))["fault_builder"]

ffibuilder = fault_builder(
    "gilfault",
    """
    #define GILFAULT_DROP_GIL_LOCKED ...
    #define GILFAULT_TAKE_GIL_HANDOVER ...
    #define GILFAULT_TAKE_GIL_CHECKING ...
    #define GILFAULT_SWITCH_MUTEX ...
    #define GILFAULT_DROP_GIL_SIGNALLING ...
    int gilfault_die_in_gil(int where);
""",
    cpython_internals=True,
    libraries=["pthread"],
)
