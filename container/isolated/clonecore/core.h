/*
 * core.h - the shapes the clone core's C files and Python share (the child's
 * control block, the configuration, the layout, the event record); what each
 * file offers is in its own header (monitor.h for monitor.c, ...), included
 * by the files that call it.  gilrepair.c and interp.c, built against
 * CPython's internal headers, share only repair.h.  The core, file by file:
 *
 *   clonecore.c  the calls Python makes: start/stop the core, spawn a child,
 *                ask it to stop, release or abandon it once reaped
 *   monitor.c    the monitor thread: performs every clone3, waits on pidfds,
 *                repairs (gilrepair.c) and reaps, reports on the event pipe
 *   child.c      how a child is born (the clone3 trampoline) and what it runs
 *                before and after the Python target (child_main)
 *   crash.c      the child's crash report, from its own signal stack
 *   dumps.c      --core-dumps: the monitor has gdb dump a crashing child
 *   contexts.c   TLS blocks (struct pthread) for children, and the allocator
 *                guard's contexts that keep one bound to a slot across children
 *   mutexes.c    native mutexes a dead child held, found through their
 *                waiters, proven, released or reported (the monitor runs it)
 *   heldscan.c   the same, held with no waiter: found by sweeping memory
 *   memwatch.c   the container's memory watch: before its memory reaches
 *                its limit, the node process that uses the most is ended
 *   listenerwait.c  Fast DDS's infinite participant-listener wait, which
 *                spins (eProsima/Fast-DDS#6513), made finite waits that sleep
 *   probes.c     small helpers assumptions.py uses to discover and check the
 *                layout, and the allocator in use
 *   pkeys.c      memory protection keys: what the machine has, and the facts
 *                per-node heap protection rests on
 *   herald.c     a node's CRASHED event, published by a thread of the core's
 *                own, without Python
 *   deathtext.c  the words for a death (the event's text and the log's)
 *   sigsafe.c    bounded text and whole writes for signal handlers and
 *                dying tasks (sigsafe.h; crash.c, deathtext.c, dumps.c, mutexes.c,
 *                gilrepair.c, lastresort.c write with it)
 *
 * x86_64 and glibc only.  Everything layout-dependent comes from
 * assumptions.py through struct cg_layout (cg_tcb_layout()), checked against a live
 * thread before anything here runs.  The extension is built with
 * -fvisibility=hidden: nothing declared here is visible outside it.
 */
#ifndef CLONEGUARD_CORE_H
#define CLONEGUARD_CORE_H

#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <Python.h>
#include <resolv.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <time.h>

#include "../allocguard/allocguard.h"
#include "repair.h"

#if !defined(__x86_64__)
#error "the clone core is x86_64 only (clone3 trampoline and TLS layout)"
#endif

/* ---------------------------------------------------------------------- */
/* Shapes shared with Python: the blocks between cdef markers are also the
   cdef of the core's cffi module (scripts/cdef.py says how it is made).   */

/* cdef: begin */
/* cdef: const SEGV_PKUERR */

#define CG_MUTEX_TYPES 4 /* NORMAL, RECURSIVE, ERRORCHECK, ADAPTIVE */
/* mutex_ret: 4 mutex types, then the condvar relock of each */
#define CG_MUTEX_CALLERS 8
#define CG_TIMED_TYPES 4 /* mutex_timed_ret: the 4 mutex types */
/* rwlock_ret: {wr,rd} x {plain, timed, clock} on a writer, + wr x ... on
   readers */
#define CG_RWLOCK_CALLERS 9
struct cg_layout { /* byte offsets from the thread pointer (= TCB) */
    long tcb, self, multiple_threads, stack_guard, pointer_guard; /* tcbhead */
    long list, tid, robust_head, specific, specific_1stblock;     /* pthread */
    long rseq_cpu_id;         /* __rseq_offset + offsetof(struct rseq, cpu_id) */
    long resp_tls;            /* &__resp (initial-exec TLS in libc) - tp */
    long robust_futex_offset; /* robust_list_head.futex_offset glibc uses */
    long cleanup;             /* struct pthread.cleanup (pthread_cleanup_push) */
    long cond_cleanup;        /* address of glibc's condvar-wait cleanup
                                 routine (cg_probe_condwait), 0: unknown */
    /* Where a task blocked on a plain mutex waits (cg_probe_mutexwait): */
    long mutex_wait_pc;               /* its pc, in __lll_lock_wait's futex call */
    long mutex_ret_slot;              /* the word above its sp holding the return
                                         address into the caller, */
    long mutex_ret[CG_MUTEX_CALLERS]; /* which is one of these: pthread_mutex_lock's
                          call for each type (0-3), pthread_cond_wait's
                          relock (CG_MUTEX_CALLERS of them) */
    long private_wait_pc;             /* pc of a task in __lll_lock_wait_private */
    /* Where a task blocked in a timed mutex lock or in a rwlock waits
       (cg_probe_timedwait); all 0: such waits are not recognized. */
    long timed_wait_pc;                       /* its pc, in __futex_abstimed_wait64's call */
    long timed_ret_slot;                      /* the word above its sp holding the return
                                                 address into the caller, */
    long mutex_timed_ret[CG_TIMED_TYPES];     /* pthread_mutex_timedlock's and
                                  _clocklock's (one shared function) for each
                                  type (0-3), */
    long rwlock_ret[CG_RWLOCK_CALLERS];       /* or pthread_rwlock_wrlock,
                                  _timedwrlock, _clockwrlock, _rdlock,
                                  _timedrdlock, _clockrdlock's, blocked on a
                                  writer, then the three writers' blocked on
                                  readers (no writer recorded), */
    long rwlock_futex_off[CG_RWLOCK_CALLERS]; /* at this offset of the
                              rwlock (its futex word minus the rwlock) */
};

#define CG_TOOL_PATH 256  /* a helper program's path (cg_config) */
#define CG_CORE_PATH 1024 /* a core dump's path (cg_child.core_path) */
#define CG_CORE_WHY 160   /* why it has none (cg_child.core_why) */
struct cg_config {        /* per CloneCore; see core.Mitigations */
    int gil_repair;
    int condvar_repair;
    int interp_repair;
    int crash_report;
    int jemalloc_own_arena; /* without alloc_guard: arenas.create in the child */
    int jemalloc_tcache;
    int alloc_guard;              /* allocguard.c is preloaded: use it (see there) */
    int mutex_repair;             /* mutexes.c: release dead children's mutexes */
    int stop_signal;              /* the test rig's stop points (stops.c): children
                                     take requests on it; 0: off */
    int core_dumps;               /* a crashing child's main task asks the monitor
                                     for a dump and waits for it (dumps.c) */
    char gdb[CG_TOOL_PATH];       /* core_dumps: gdb's absolute path, */
    char fallocate[CG_TOOL_PATH]; /* and fallocate's ("": none, the dump
                                     keeps its runs of zeros) */
};

enum { CG_EV_DEATH = 1, CG_EV_STOP = 2, CG_EV_CLOSED = 3, CG_EV_MUTEX = 4 };
struct cg_event { /* one record on the event pipe: 64 bytes */
    uint32_t kind;
    int32_t pid;    /* death, stop: the child; mutex: the dead child
                       that held it (the last one to die if none
                       is proven) */
    int32_t status; /* death: si_status; stop: CG_STOP_*;
                       mutex: CG_MUTEX_* (what was done) */
    int32_t code;   /* death: si_code (CLD_EXITED/KILLED/DUMPED),
                       0 if someone else reaped the child;
                       stop: the signal (0: asked by the parent);
                       mutex: its __data.__kind, -1: not a
                       pthread mutex (a glibc-internal lock),
                       CG_RWLOCK_KIND: a pthread_rwlock_t */
    uint64_t serial;
    int64_t t_ns;     /* CLOCK_MONOTONIC when the monitor noticed */
    uint32_t repairs; /* death: CG_REPAIR_* (repair.h) */
    uint32_t alloc;   /* death: its allocator slot (CG_ALLOC_SLOT_MASK,
                         0: none) | CG_ALLOC_* */
    uint64_t addr;    /* mutex: its address (the lock word's) */
    int32_t tid;      /* mutex: the task blocked on it */
    int32_t owner;    /* mutex: its owner's tid, 0: none recorded */
    uint32_t flags;   /* death: CG_EVF_* */
};
#define CG_RWLOCK_KIND (-2)     /* cg_event.code of a rwlock (mutexes.c) */
#define CG_EVF_CLAIMED 1u       /* its CRASHED event is the herald's (herald.c) */
#define CG_EVF_OUT_OF_MEMORY 2u /* the memory watch ended it (memwatch.c) */
#define CG_DEATH_TEXT 768       /* cg_child.death_text */
/* What the lock doctor did about a task blocked on a lock (mutexes.c). */
enum {
    CG_MUTEX_RELEASED = 1,  /* plain mutex of a proven-dead owner: released */
    CG_MUTEX_UNPROVEN = 2,  /* its owner is gone, not proven a dead child's */
    CG_MUTEX_NO_OWNER = 3,  /* held, no owner recorded, for over a second */
    CG_MUTEX_EXCLUDED = 4,  /* a dead owner's robust/PI/shared/elided mutex */
    CG_MUTEX_LIBC_LOCK = 5, /* a glibc-internal lock waited on for over a
                               second after a death (no owner recorded) */
};
/* cg_event.alloc of a death: its slot in the low bits, and above
   CG_ALLOC_SHIFT what its process left (cga_slot_retire's CGA_RETIRE_*
   bits, allocguard.h, as they are). */
#define CG_ALLOC_SLOT_MASK 0xffffu
#define CG_ALLOC_SHIFT 28
#define CG_ALLOC_QUARANTINED ((uint32_t)CGA_RETIRE_QUARANTINED << CG_ALLOC_SHIFT)
#define CG_ALLOC_PY_ABANDONED ((uint32_t)CGA_RETIRE_PY_ABANDONED << CG_ALLOC_SHIFT)
#define CG_ALLOC_FAULTED ((uint32_t)CGA_RETIRE_FAULTED << CG_ALLOC_SHIFT)
#define CG_ALLOC_OVER_BUDGET ((uint32_t)CGA_RETIRE_OVER_BUDGET << CG_ALLOC_SHIFT)
/* cdef: end */
_Static_assert(CGA_RETIRE_OVER_BUDGET < (1 << (32 - CG_ALLOC_SHIFT)),
               "CGA_RETIRE_* fit above the slot");

/* cdef: begin */

enum { CG_STOP_NONE = 0, CG_STOP_PARENT = 1, CG_STOP_SIGNAL = 2 };
enum { CG_RUNNING = 0, CG_REAPED = 1 };
enum { CG_PY_NOT_YET = 0, CG_PY_INSIDE = 1, CG_PY_LEFT = 2 };
#define CG_CRASH_FRAMES 64     /* native frames a crash report keeps */
#define CG_CRASH_PY_FRAMES 100 /* Python frames (faulthandler's depth too) */
#define CG_FLAG_ALLOW_CORE 1   /* experiments only: leave RLIMIT_CORE alone */
/* cg_child.core_dump (dumps.c): asked, then written or not (core_why) */
#define CG_CORE_NONE 0
#define CG_CORE_ASKED 1
#define CG_CORE_DONE 2
#define CG_CORE_FAILED 3
#define CG_CORE_WAIT_S 600     /* how long a crashing child waits for its dump */
#define CG_GO_STOP 0x80000000u /* cg_child.go: every wait at the gate ends */
/* cdef: end */

/* The tasks the monitor saw in a child (mutexes.c): each tid with where the
   kernel's pid cursor stood when it was last seen alive. */
#define CG_SEEN_TASKS 256
struct cg_seen_task {
    int tid;
    int cursor;        /* ns_last_pid then */
    uint64_t advanced; /* how far the cursor had moved in all, then */
};
struct cg_seen_tasks {
    int n;
    int overflow; /* more tasks than CG_SEEN_TASKS were alive */
    struct cg_seen_task t[CG_SEEN_TASKS];
};

/* cdef: begin */
struct cg_child { /* control block, lives in container memory */
    /* read by Python */
    int pid;
    int pidfd;
    uint64_t serial; /* Python's name for the child */
    int64_t start_ns;
    int state;          /* CG_RUNNING / CG_REAPED (atomic): reported dead,
                           forgotten by the monitor; a zombie until
                           cg_release or cg_abandon reaps it */
    int stop_requested; /* CG_STOP_* (atomic; child, parent, monitor) */
    int py_phase;       /* CG_PY_* (atomic; written by the child) */
    int stop_signal;    /* the signal that asked (atomic), 0: parent */
    int arena;          /* jemalloc arena the child bound to, -1: none */
    /* written by its crash report (crash.c; crash_tid below), read by
       Python once reaped */
    int crash_si_code;                       /* the fault's si_code (SEGV_PKUERR: 4), */
    int crash_sender;                        /* who sent it (si_code <= 0), else 0, */
    int crash_pkey;                          /* its key (SEGV_PKUERR), */
    void *crash_addr;                        /* and its address */
    int crash_nframes;                       /* 0: none; -1: being written; else how many */
    void *crash_frames[CG_CRASH_FRAMES];     /* the crashing task's native stack */
    int crash_py_nframes;                    /* its Python stack: how many frames, */
    int crash_py_more;                       /* 1: it went on past CG_CRASH_PY_FRAMES */
    void *crash_py_code[CG_CRASH_PY_FRAMES]; /* each frame's code object */
    int crash_py_lasti[CG_CRASH_PY_FRAMES];  /* and instruction offset */
    /* written by the repair (monitor) if it died holding the GIL: its
       innermost Python frame, read by Python once reaped */
    void *gil_code;
    int gil_lasti;
    /* --core-dumps (dumps.c): CG_CORE_*; the crashing main task waits in
       its crash handler while the monitor has its dump written */
    int core_dump;
    char core_path[CG_CORE_PATH]; /* where (Python names it; "": nowhere) */
    char core_why[CG_CORE_WHY];   /* CG_CORE_FAILED: why */
    int herald_state;             /* herald.c: who owns its CRASHED event (atomic) */
    /* written by the monitor at its death (cg_describe_death), read by
       Python once reported */
    char death_text[CG_DEATH_TEXT];
    /* cdef: the rest is the core's */
    unsigned go;       /* futex word: how many times the parent said
                          go (cg_go), | CG_GO_STOP once asked to stop */
    unsigned go_taken; /* how many of those the child has waited for */
    /* set up before the clone */
    PyObject *target;      /* borrowed: Python keeps it alive until reaped */
    PyThreadState *tstate; /* made by cg_spawn, deleted by cg_release */
    int flags;
    int cgroup_fd; /* -1: stay in the container's cgroup */
    int parent_tgid;
    char *map; /* guard page + stack */
    size_t map_len, stack_size;
    char *alt; /* guard page + signal stack (crash reports) */
    size_t alt_len;
    char *tcb;          /* from _dl_allocate_tls (or ctx->tcb) */
    struct cg_ctx *ctx; /* with the allocator guard: its context */
    /* monitor-only */
    int stop_reported;
    int repair_done;     /* gilrepair has looked at this dead child */
    int gil_ref_dropped; /* its crashing main task, waiting for its
                            dump, no longer holds up the GIL's condvar
                            (repair_step_aside) */
    uint32_t repairs;    /* what it repaired for it */
    int retired;         /* CGA_RETIRE_* (allocguard.h): what it left in
                            the allocator guard, once reaped */
    struct cg_child *next;
    struct cg_seen_tasks seen;  /* its tasks, as the monitor saw them */
    int crash_tid;              /* crash.c: the task that caught it */
    struct cg_child *dump_next; /* dumps.c: the monitor's queue of dumps */
    struct cg_herald *herald;   /* herald.c: its CRASHED event */
    /* memwatch.c: its oom_score_adj (atomic; set before it goes), and what
       the watch saw when it ended it (monitor-only; oom_in_use 0: it did not) */
    int oom_score_adj;
    uint64_t oom_used, oom_in_use;
    /* the child's own resolver state, as start_thread gives each thread */
    struct __res_state res;
};

/* A pthread_cond_wait that is blocked, seen from outside: glibc 2.36 pushes
   a cleanup record (struct pthread.cleanup) whose argument says which
   condvar, which mutex and which position it waits at, and it holds a
   reference on its condvar group meanwhile.  gilrepair.c relies on all of
   that for dead waiters; cg_probe_condwait (probes.c) checks it on a live pthread at start-up. */
struct cg_condwait_probe {
    uintptr_t routine; /* the cleanup routine the waiter pushed */
    int found;         /* TCB+cleanup became non-NULL while it waited */
    int buf_on_stack;  /* the record lies on the waiter's stack */
    int cbuf_matches;  /* its argument names our cond and mutex */
    int wseq_matches;  /* argument.wseq + 2 == cond.__wseq (1 waiter) */
    int holds_ref;     /* cond.__g_refs[group] == 2 while it waits */
    int routine_in_libc;
    int cleared_after; /* TCB+cleanup is back to what it was before */
};

/* A glibc mutex waiter as the monitor sees it from outside
   (cg_probe_mutexwait checks all of it on live pthreads). */
struct cg_mutexwait_probe {
    int self_tid;
    int seen[CG_MUTEX_CALLERS];                      /* the waiter was found in futex(&m) */
    int op[CG_MUTEX_CALLERS], val[CG_MUTEX_CALLERS]; /* its futex op, value */
    uintptr_t pc[CG_MUTEX_CALLERS];
    int ret_slot[CG_MUTEX_CALLERS]; /* where its return address was found */
    uintptr_t ret[CG_MUTEX_CALLERS];
    int ret_in_libc[CG_MUTEX_CALLERS];
    int kind[CG_MUTEX_CALLERS];          /* the mutex's __kind while held */
    int owner_is_self[CG_MUTEX_CALLERS]; /* its __owner was the holder */
    int private_seen, private_op, private_val;
    uintptr_t private_pc; /* ... in __lll_lock_wait_private */
};

/* Timed mutex waiters and rwlock waiters blocked on a writer, as the monitor
   sees them from outside (cg_probe_timedwait checks them on live pthreads).
   Mutex probe k: type k / 2, k % 2 == 0 pthread_mutex_timedlock
   (CLOCK_REALTIME), 1 pthread_mutex_clocklock(CLOCK_MONOTONIC).  Rwlock
   probe k: the order of cg_layout.rwlock_ret. */
#define CG_TIMED_PROBES (2 * CG_TIMED_TYPES)
struct cg_timedwait_probe {
    int self_tid;
    int seen[CG_TIMED_PROBES];
    int op[CG_TIMED_PROBES], val[CG_TIMED_PROBES];
    uintptr_t pc[CG_TIMED_PROBES];
    int ret_slot[CG_TIMED_PROBES];    /* = rw_ret_slot[0] */
    uintptr_t ret[CG_TIMED_PROBES];   /* the word there, */
    int ret_in_libc[CG_TIMED_PROBES]; /* which lies in libc */
    int kind[CG_TIMED_PROBES];        /* the mutex's __kind while held */
    int owner_is_self[CG_TIMED_PROBES];
    int rw_seen[CG_RWLOCK_CALLERS];
    int rw_op[CG_RWLOCK_CALLERS], rw_val[CG_RWLOCK_CALLERS];
    uintptr_t rw_pc[CG_RWLOCK_CALLERS];
    long rw_futex_off[CG_RWLOCK_CALLERS]; /* futex word - rwlock */
    int rw_ret_slot[CG_RWLOCK_CALLERS];   /* the word into the function
                                             (by dladdr), */
    uintptr_t rw_ret[CG_RWLOCK_CALLERS];
    int rw_writer_recorded[CG_RWLOCK_CALLERS]; /* __cur_writer = the writer
                               (0 while readers hold it: k >= 6) */
    int rw_released[CG_RWLOCK_CALLERS];        /* a thread that made itself
                                   __cur_writer and called pthread_rwlock_unlock
                                   after the writer ended let the waiter in */
    long off_wrphase_futex, off_writers_futex; /* offsetof in the rwlock */
};

/* cdef: end */

/* A task's system call as /proc/<tid>/syscall shows it. */
struct task_syscall {
    long nr; /* -1: blocked outside a syscall, -2: running
                or unreadable */
    uintptr_t args[6];
    uintptr_t sp, pc;
};

/* With the guard, a child runs in a *context*: a TLS block (struct pthread
   + static TLS) and the allocator slot bound to it, whose thread cache,
   arena binding and (glibc) arena live in that TLS block.  A context whose
   child ended outside the allocator is reused by the next child, with all
   of that in place; one whose child died inside the allocator is never
   touched again (its TLS block stays allocated: jemalloc keeps a list of
   every thread's data, this one included).  contexts.c. */
struct cg_ctx {
    char *tcb;
    int slot;
    struct cg_ctx *next;
};

#define AT(base, off, type) (*(type *)((char *)(base) + (off)))

/* ---- Among the core's files ------------------------------------------- */

/* CLOCK_MONOTONIC in ns (the monitor's clock, listenerwait.c's). */
static inline int64_t cg_mono_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}
#define MIB ((uint64_t)1 << 20) /* bytes, in the words for a death */
/* jemalloc's mallctl (cg_mallctl, find_mallctl). */
typedef int (*mallctl_fn)(const char *, void *, size_t *, void *, size_t);

#endif
