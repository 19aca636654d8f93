"""cffi (API mode) builder for container.isolated._clonecore.

The C lives next to this file, one job per file (core.h lists them): the
generated module includes core.h, the declarations Python's calls need, and
links the core's files as further sources; gilrepair.c is among them,
compiled with Py_BUILD_CORE (it reads CPython's internal GIL state; see
there), sharing only repair.h with the rest.  The cdef below mirrors the
public part of all of them: keep them in step (a function's mismatch is a
compile error in the generated module; a struct's, "wrong total size" at its
first ffi.new, when the core starts).  Built with -fvisibility=hidden: the module
exports its PyInit function only.

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

CDEF = r"""
struct cg_layout {
    long tcb, self, multiple_threads, stack_guard, pointer_guard;
    long list, tid, robust_head, specific, specific_1stblock;
    long rseq_cpu_id;
    long resp_tls;
    long robust_futex_offset;
    long cleanup;
    long cond_cleanup;
    long mutex_wait_pc;
    long mutex_ret_slot;
    long mutex_ret[8];
    long private_wait_pc;
    long timed_wait_pc;
    long timed_ret_slot;
    long mutex_timed_ret[4];
    long rwlock_ret[9];
    long rwlock_futex_off[9];
};

struct cg_config {
    int gil_repair;
    int condvar_repair;
    int interp_repair;
    int crash_report;
    int jemalloc_own_arena;
    int jemalloc_tcache;
    int alloc_guard;
    int mutex_repair;
    int stop_signal;
    int core_dumps;
    char gdb[256];
    char fallocate[256];
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
    uint64_t addr;
    int32_t tid;
    int32_t owner;
    uint32_t flags;
};

struct cga_py_stats {
    unsigned generation;
    uint64_t pools;
    uint64_t handed;
    uint64_t dropped;
    uint64_t abandoned;
};

struct cga_slot_stats {
    int state;
    int pid;
    unsigned arena;
    int glibc_arenas;
    uint64_t handed_blocks;
    uint64_t pending_blocks;
    uint64_t pending_bytes;
    uint64_t held_blocks;
    uint64_t held_bytes;
    uint64_t main_arena_allocs;
};

struct cga_slot_memory {
    uint64_t in_use;
    uint64_t limit;
    uint64_t over_used;
    uint64_t over_asked;
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

struct cg_mutexwait_probe {
    int self_tid;
    int seen[8];
    int op[8], val[8];
    uintptr_t pc[8];
    int ret_slot[8];
    uintptr_t ret[8];
    int ret_in_libc[8];
    int kind[8];
    int owner_is_self[8];
    int private_seen, private_op, private_val;
    uintptr_t private_pc;
};

struct cg_timedwait_probe {
    int self_tid;
    int seen[8];
    int op[8], val[8];
    uintptr_t pc[8];
    int ret_slot[8];
    uintptr_t ret[8];
    int ret_in_libc[8];
    int kind[8];
    int owner_is_self[8];
    int rw_seen[9];
    int rw_op[9], rw_val[9];
    uintptr_t rw_pc[9];
    long rw_futex_off[9];
    int rw_ret_slot[9];
    uintptr_t rw_ret[9];
    int rw_writer_recorded[9];
    int rw_released[9];
    long off_wrphase_futex, off_writers_futex;
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

struct cg_interp_probe {
    int threshold[3], count[3];
    int generation0_is_head;
    int enabled, collecting;
    int young_links_ok;
    int free_lists_ok;
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
    int crash_si_code;
    int crash_sender;
    int crash_pkey;
    void *crash_addr;
    int crash_nframes;
    void *crash_frames[...];
    int crash_py_nframes;
    int crash_py_more;
    void *crash_py_code[...];
    int crash_py_lasti[...];
    void *gil_code;
    int gil_lasti;
    int core_dump;
    char core_path[1024];
    char core_why[160];
    int herald_state;
    char death_text[768];
    ...;
};

/* discovery helpers (assumptions.py) */
uintptr_t cg_thread_pointer(void);
uintptr_t cg_robust_list_head(void);
long cg_gettid(void);
void *cg_lookup(const char *name, const char *version);
long cg_mutex_futex_offset(void);
int cg_probe_clone3(void);

struct cg_pkeys_probe {
    int cpu_pku, os_pke;
    int keys;
    int alloc_errno;
    uint32_t pkru;
    int mprotect_keeps;
    int thread_inherits;
    int write_faults;
};
int cg_pkeys_probe(struct cg_pkeys_probe *out);
int cg_pkeys_in_use(int *keys, int max);
int cg_alloc_slot_of(const void *p);
int cg_child_slot(const struct cg_child *c);
int cg_child_set_memory_limit(const struct cg_child *c, uint64_t bytes);
int cg_memwatch_set(int usage_fd, int stat_fd, const char *stat_key, int meminfo, uint64_t limit,
                    uint64_t margin);
int cg_child_set_oom_score_adj(struct cg_child *c, int adj);
int cg_child_memory(const struct cg_child *c, struct cga_slot_memory *out);
int cg_probe_condwait(long cleanup_off, struct cg_condwait_probe *out);
int cg_probe_mutexwait(struct cg_mutexwait_probe *out);
int cg_probe_timedwait(struct cg_timedwait_probe *out);
int cg_gil_probe(struct cg_gil_probe *out);
int cg_interp_probe(struct cg_interp_probe *out);
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
int cg_container_crash_report(void);
int cg_record_py_stack(void **codes, int *lasti, int max, int *more);
void cg_hold_py_stack(void *const *codes, int n, int hold);
void cg_write_py_stack(void *const *codes, const int *lasti, int n, int more, int fd);
int cg_frame_text(void *code, int lasti, char *buf, int size);
int cg_alloc_slot_stats(int slot, struct cga_slot_stats *out);
int cg_py_slot_stats(int slot, struct cga_py_stats *out);
int cg_gc_wait_due(int interval_us, int *wake);
long cg_gc_collect(void *collect, int generation);
int cg_bound_listener_wait(char *why_out, int why_size);
const char *cg_repair_name(unsigned bit);
int cg_describe_death(int status, int code, uint32_t repairs, uint32_t alloc,
                      int stop_signal, char *out, int size);
int cg_herald_start(void *publish, const void *publisher);
int cg_herald_stop(int timeout_ms);
long cg_herald_failures(void);
int cg_herald_arm(struct cg_child *c, uint64_t unique_id, const char *full_node_name,
                  const char *package_name, const char *plugin_name, int pid,
                  uint64_t start_time_ns);
int cg_herald_disarm(struct cg_child *c);
int cg_herald_claimed(const struct cg_child *c);
long cg_listener_waits_bounded(void);
int64_t cg_watch_clock_ns(void);
int cg_lastresort_start(int fd, const char *banner);
void cg_lastresort_arm(int64_t after_ns);
void cg_lastresort_stop(void);

#define SEGV_PKUERR ... /* si_code of a SIGSEGV a protection key raised */
#define CG_EV_DEATH ...
#define CG_EV_STOP ...
#define CG_EV_CLOSED ...
#define CG_EV_MUTEX ...
#define CG_EVF_ANNOUNCED ...
#define CG_EVF_OUT_OF_MEMORY ...
#define CG_DEATH_TEXT ...
#define CG_CORE_NONE ...
#define CG_CORE_DONE ...
#define CG_CORE_FAILED ...
#define CG_TOOL_PATH ...
#define CG_CORE_PATH ...
#define CG_MUTEX_CALLERS ...
#define CG_TIMED_TYPES ...
#define CG_TIMED_PROBES ...
#define CG_RWLOCK_CALLERS ...
#define CG_RWLOCK_KIND ...
#define CG_MUTEX_RELEASED ...
#define CG_MUTEX_UNPROVEN ...
#define CG_MUTEX_NO_OWNER ...
#define CG_MUTEX_EXCLUDED ...
#define CG_MUTEX_LIBC_LOCK ...
#define CG_STOP_PARENT ...
#define CG_STOP_SIGNAL ...
#define CG_REAPED ...
#define CG_FLAG_ALLOW_CORE ...
#define CG_CRASH_FRAMES ...
#define CG_ALLOC_SLOT_MASK ...
#define CG_ALLOC_QUARANTINED ...
#define CG_ALLOC_PY_ABANDONED ...
#define CG_ALLOC_FAULTED ...
#define CG_ALLOC_OVER_BUDGET ...
#define CGA_UNUSED ...
#define CGA_IDLE ...
#define CGA_BOUND ...
#define CGA_QUARANTINED ...
#define CGA_STOP_ALLOCATION ...
#define CGA_STOP_PY_ALLOCATION ...
#define CGA_STOP_PY_LOCK ...
#define CGA_STOP_PLACE_BITS ...
#define CGA_STOP_KEY_SHIFT ...
#define CG_REPAIR_GIL_RELEASED ...
#define CG_REPAIR_GIL_MUTEX ...
#define CG_REPAIR_SWITCH_MUTEX ...
#define CG_REPAIR_COND_WAITER ...
#define CG_REPAIR_SWITCH_WAITER ...
#define CG_REPAIR_COND_LOCK ...
#define CG_REPAIR_GIL_TIMEOUT ...
#define CG_REPAIR_PY_POOLS ...
#define CG_REPAIR_GC_LINKS ...
#define CG_REPAIR_FREELISTS ...
#define CG_REPAIR_PY_OBJECTS ...
"""

ffibuilder = FFI()
ffibuilder.cdef(CDEF)
ffibuilder.set_source(
    "cloneguard.container.isolated._clonecore",
    '#include "core.h"\n' + CFLAGS["cffi_init_prototype"]("cloneguard.container.isolated._clonecore"),
    # setuptools wants sources relative to the repo root (where setup.py runs).
    sources=[f"container/isolated/{n}" for n in SOURCES],
    include_dirs=[str(HERE)],
    depends=[f"container/isolated/{n}" for n in ("core.h", "repair.h", "allocguard.h", "sigsafe.h")],
    libraries=["dl", "pthread"],
    extra_compile_args=["-std=gnu11", *WARNINGS, "-Wno-unused-function", "-fvisibility=hidden"],
    # The C uses the non-limited C API (PyThreadState fields): cffi would
    # otherwise define Py_LIMITED_API (the macro covers ffibuilder.compile(),
    # the keyword a setuptools build).
    define_macros=[("_CFFI_NO_LIMITED_API", None)],
    py_limited_api=False,
)
