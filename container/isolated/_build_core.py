"""cffi (API mode) builder for container.isolated._clonecore.

The C lives next to this file, one job per file (core.h lists them): the
generated module includes core.h, the declarations Python's calls need, and
links the core's files as further sources; gilrepair.c is among them,
compiled with Py_BUILD_CORE (it reads CPython's internal GIL state; see
there), sharing only clonecore.h with the rest.  The cdef below mirrors the
public part of all of them: keep them in step (a mismatch is a compile error
in the generated module).  Built with -fvisibility=hidden: the module
exports its PyInit function only.

Built by setup.py (``cffi_modules``); after an edit of the C,
``pip install --no-build-isolation --no-deps -e .`` rebuilds it in place.
"""

from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent
SOURCES = ("clonecore.c", "monitor.c", "child.c", "crash.c", "contexts.c", "probes.c", "gilrepair.c")

CDEF = r"""
struct cg_layout {
    long tcb, self, multiple_threads, stack_guard, pointer_guard;
    long list, tid, robust_head, specific, specific_1stblock;
    long rseq_cpu_id;
    long resp_tls;
    long robust_futex_offset;
    long cleanup;
    long cond_cleanup;
};

struct cg_config {
    int gil_repair;
    int condvar_repair;
    int crash_report;
    int jemalloc_own_arena;
    int jemalloc_tcache;
    int alloc_guard;
};

struct cg_event {
    uint32_t kind;
    int32_t pid;
    int32_t status;
    int32_t code;
    uint64_t serial;
    int64_t t_ns;
    uint32_t repairs;
    uint32_t alloc;
};

struct cga_slot_stats {
    int state;
    int pid;
    unsigned arena;
    int glibc_arenas;
    uint64_t handed_blocks;
    uint64_t pending_blocks;
    uint64_t pending_bytes;
    uint64_t main_arena_allocs;
};

struct cg_condwait_probe {
    uintptr_t routine;
    int found;
    int buf_on_stack;
    int cbuf_matches;
    int wseq_matches;
    int holds_ref;
    int routine_in_libc;
    int cleared_after;
};

struct cg_gil_probe {
    unsigned long compiled_hex, running_hex;
    long runtime_size_compiled, runtime_size_elf;
    int locked;
    int last_holder_is_me, tstate_current_is_me;
    int native_id_ok, thread_id_ok;
    int mutex_kind, switch_mutex_kind;
    int cond_wrefs_flags, switch_cond_wrefs_flags;
    long gil_offset, mutex_offset, cond_offset;
};

struct cg_child {
    int pid;
    int pidfd;
    uint64_t serial;
    int64_t start_ns;
    int state;
    int stop_requested;
    int py_phase;
    int stop_signal;
    int arena;
    int crash_nframes;
    void *crash_frames[...];
    int crash_py_nframes;
    int crash_py_more;
    void *crash_py_code[...];
    int crash_py_lasti[...];
    ...;
};

/* discovery helpers (assumptions.py) */
uintptr_t cg_thread_pointer(void);
uintptr_t cg_robust_list_head(void);
long cg_gettid(void);
void *cg_lookup(const char *name, const char *version);
long cg_mutex_futex_offset(void);
int cg_probe_clone3(void);
int cg_probe_condwait(long cleanup_off, struct cg_condwait_probe *out);
int cg_gil_probe(struct cg_gil_probe *out);
int cg_allocator(char *buf, size_t len);
int cg_jemalloc_thread_arena(void);
int cg_jemalloc_thread_tcache(void);

/* monitor and children */
int cg_start(const struct cg_layout *layout, const struct cg_config *cfg,
             int *event_fd);
int cg_stop(void);
int cg_spawn(void *target, uint64_t serial, size_t stack_size, int cgroup_fd,
             int flags, struct cg_child **out);
int cg_request_stop(struct cg_child *c);
int cg_go(struct cg_child *c);
int cg_release(struct cg_child *c);
int cg_abandon(struct cg_child *c);
int cg_self_stop_requested(void);
int cg_self_wait_go(void);
void cg_write_native_stack(void *const *frames, int n, int fd);
int cg_record_py_stack(void **codes, int *lasti, int max, int *more);
void cg_hold_py_stack(void *const *codes, int n, int hold);
void cg_write_py_stack(void *const *codes, const int *lasti, int n, int more, int fd);
int cg_alloc_slot_stats(int slot, struct cga_slot_stats *out);

#define CG_EV_DEATH ...
#define CG_EV_STOP ...
#define CG_EV_CLOSED ...
#define CG_STOP_PARENT ...
#define CG_STOP_SIGNAL ...
#define CG_REAPED ...
#define CG_FLAG_ALLOW_CORE ...
#define CG_CRASH_FRAMES ...
#define CG_ALLOC_QUARANTINED ...
#define CGA_UNUSED ...
#define CGA_IDLE ...
#define CGA_BOUND ...
#define CGA_QUARANTINED ...
#define CG_REPAIR_GIL_RELEASED ...
#define CG_REPAIR_GIL_MUTEX ...
#define CG_REPAIR_SWITCH_MUTEX ...
#define CG_REPAIR_COND_WAITER ...
#define CG_REPAIR_SWITCH_WAITER ...
#define CG_REPAIR_COND_LOCK ...
#define CG_REPAIR_GIL_TIMEOUT ...
"""

ffibuilder = FFI()
ffibuilder.cdef(CDEF)
ffibuilder.set_source(
    "cloneguard.container.isolated._clonecore",
    '#include "core.h"\n',
    # setuptools wants sources relative to the repo root (where setup.py runs).
    sources=[f"container/isolated/{n}" for n in SOURCES],
    include_dirs=[str(HERE)],
    depends=[f"container/isolated/{n}" for n in ("core.h", "clonecore.h", "allocguard.h")],
    libraries=["dl", "pthread"],
    extra_compile_args=["-std=gnu11", "-Wall", "-Wno-unused-function", "-fvisibility=hidden"],
    # The C uses the non-limited C API (PyThreadState fields): cffi would
    # otherwise define Py_LIMITED_API (the macro covers ffibuilder.compile(),
    # the keyword a setuptools build).
    define_macros=[("_CFFI_NO_LIMITED_API", None)],
    py_limited_api=False,
)
