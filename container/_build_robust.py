"""cffi (API mode) builder for container._robust (robust.c: robust mutexes)."""
from pathlib import Path

from cffi import FFI

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
    extra_compile_args=["-std=gnu11", "-Wall"],
)
