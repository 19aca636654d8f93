"""cffi (API mode) builder for faults._interpfault (interpfault.c: die half-way
through changing the interpreter's state)."""

import runpy
from pathlib import Path

fault_builder = runpy.run_path(str(Path(__file__).with_name("_cffi_fault.py")))["fault_builder"]

ffibuilder = fault_builder(
    "interpfault",
    """
    int interpfault_die_mid_gc_untrack(int stores);
    int interpfault_die_mid_gc_track(int stores);
    int interpfault_die_mid_list_append(void *list);
    int interpfault_die_with_torn_locals(void);
    int interpfault_die_inside(const char *library, int period_us, long max_ticks);
""",
    cpython_internals=True,
)
