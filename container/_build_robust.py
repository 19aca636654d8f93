"""cffi (API mode) builder for container._robust (robust.c: robust mutexes)."""

import runpy
from pathlib import Path

from cffi import FFI

# The project's C warning flags: one list for every build (scripts/cflags.py).
WARNINGS = runpy.run_path(str(Path(__file__).resolve().parents[1] / "scripts" / "cflags.py"))["WARNINGS"]

HERE = Path(__file__).resolve().parent

ffibuilder = FFI()
ffibuilder.cdef("""
    typedef struct { ...; } pthread_mutex_t;
    pthread_mutex_t *rm_new(void);
    void rm_free(pthread_mutex_t *m);
    int rm_lock(pthread_mutex_t *m, int64_t timeout_ns);
    int rm_trylock(pthread_mutex_t *m);
    int rm_consistent(pthread_mutex_t *m);
    int rm_unlock(pthread_mutex_t *m);
""")
ffibuilder.set_source(
    "cloneguard.container._robust",
    '#include "robust.c"\n',
    include_dirs=[str(HERE)],
    depends=[str(HERE / "robust.c")],
    libraries=["pthread"],
    extra_compile_args=["-std=gnu11", *WARNINGS],
)
