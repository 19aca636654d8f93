"""cffi (API mode) builder for faults._hammer (the malloc hammer, hammer.c)."""

import runpy
from pathlib import Path

from cffi import FFI

# The project's C warning flags: one list for every build (scripts/cflags.py).
WARNINGS = runpy.run_path(str(Path(__file__).resolve().parents[1] / "scripts" / "cflags.py"))["WARNINGS"]

HERE = Path(__file__).resolve().parent

ffibuilder = FFI()
ffibuilder.cdef("""
    int hammer_run(int ring, uint64_t seed);
    long drain_some(int ring);
    uint64_t hammer_ops_done(int ring);
    void hammer_burst(uint64_t seed, long pairs);
    int64_t hammer_pairs(size_t size, long n);
    int64_t hammer_alloc_many(void **out, size_t size, long n);
    int64_t hammer_free_many(void **blocks, long n);
""")
ffibuilder.set_source(
    "cloneguard.faults._hammer",
    '#include "hammer.c"\n',
    include_dirs=[str(HERE)],
    depends=[str(HERE / "hammer.c")],
    extra_compile_args=["-O2", "-std=gnu11", *WARNINGS],
)
