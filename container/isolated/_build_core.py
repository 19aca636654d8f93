"""cffi (API mode) builder for container.isolated._clonecore.

The C lives in clonecore.c next to this file; the generated module just
#includes it, so compiler messages point at clonecore.c lines.  The cdef below
mirrors the public part of clonecore.c: keep the two in step (a mismatch is a
compile error in the generated module).

Built by setup.py (``cffi_modules``); ``python container/isolated/_build_core.py``
also builds it in place for quick iteration.
"""

from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent

CDEF = r"""
struct cg_layout {
    long tcb, self, multiple_threads, stack_guard, pointer_guard;
    long list, tid, robust_head, specific, specific_1stblock;
    long rseq_cpu_id;
    long resp_tls;
    long robust_futex_offset;
};

struct cg_event {
    uint32_t kind;
    int32_t pid;
    int32_t status;
    int32_t code;
    uint64_t serial;
    int64_t t_ns;
};

struct cg_child {
    int pid;
    int pidfd;
    uint64_t serial;
    int64_t start_ns;
    int state;
    int stop_requested;
    int py_phase;
    ...;
};

/* discovery helpers (assumptions.py) */
uintptr_t cg_thread_pointer(void);
uintptr_t cg_robust_list_head(void);
long cg_gettid(void);
void *cg_lookup(const char *name, const char *version);
long cg_mutex_futex_offset(void);
int cg_probe_clone3(void);

/* monitor and children */
int cg_start(const struct cg_layout *layout, int *event_fd);
int cg_stop(void);
int cg_spawn(void *target, uint64_t serial, size_t stack_size, int cgroup_fd,
             int flags, struct cg_child **out);
int cg_request_stop(struct cg_child *c);
int cg_release(struct cg_child *c);
int cg_self_stop_requested(void);

/* robust mutexes */
typedef struct { ...; } pthread_mutex_t;
pthread_mutex_t *cg_rmutex_new(void);
void cg_rmutex_free(pthread_mutex_t *m);
int cg_rmutex_lock(pthread_mutex_t *m, int64_t timeout_ns);
int cg_rmutex_trylock(pthread_mutex_t *m);
int cg_rmutex_consistent(pthread_mutex_t *m);
int cg_rmutex_unlock(pthread_mutex_t *m);

#define CG_EV_DEATH ...
#define CG_EV_STOP ...
#define CG_EV_CLOSED ...
#define CG_STOP_PARENT ...
#define CG_STOP_SIGNAL ...
#define CG_REAPED ...
#define CG_FLAG_ALLOW_CORE ...
"""

ffibuilder = FFI()
ffibuilder.cdef(CDEF)
ffibuilder.set_source(
    "container.isolated._clonecore",
    '#include "clonecore.c"\n',
    include_dirs=[str(HERE)],
    depends=[str(HERE / "clonecore.c")],
    libraries=["dl", "pthread"],
    extra_compile_args=["-std=gnu11", "-Wall", "-Wno-unused-function"],
    # The C uses the non-limited C API (PyThreadState fields): cffi would
    # otherwise define Py_LIMITED_API.
    py_limited_api=False,
)

if __name__ == "__main__":
    import os

    os.chdir(HERE.parent.parent)  # the repo root: the module lands in place
    ffibuilder.compile(verbose=True)
