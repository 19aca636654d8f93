/*
 * repair.h - what the clone core and its repairers built with
 * Py_BUILD_CORE (gilrepair.c: the GIL; interp.c: the interpreter) share:
 * the repair bits a death reports, what is known of a dead task, glibc's
 * condvar waiter record.  Shapes that Python sees are mirrored in
 * _build_core.py's cdef.
 */
#ifndef CLONEGUARD_REPAIR_H
#define CLONEGUARD_REPAIR_H

#include <stdbool.h>
#include <stdint.h>
#include <sys/types.h>

/* What the monitor repaired after a death (struct cg_event.repairs): each
   repair's name and bit, written here only.  deathtext.c's words take the
   names from it (cg_repair_name), core_events.Repair its members (checked
   against cg_repair_name by tests/test_herald.py).
     GIL_RELEASED   the dead task held the GIL
     GIL_MUTEX      ... or gil->mutex
     SWITCH_MUTEX   ... or gil->switch_mutex
     COND_WAITER    it was blocked on gil->cond
     SWITCH_WAITER  it was blocked on gil->switch_cond
     COND_LOCK      a condvar's internal lock stayed taken: cleared
     GIL_TIMEOUT    gil->mutex could not be taken to check the GIL: nothing
                    checked
   interp.c, when the dead task held the GIL:
     PY_POOLS       its Python object pools abandoned, their objects
                    untracked before the next collection
     GC_LINKS       a half-updated link of the young generation mended
     FREELISTS      the interpreter's free lists emptied
     PY_OBJECTS     objects it may have been changing put out of the
                    collector's sight */
/* cdef: begin */
#define CG_REPAIRS(X)                                                                              \
    X(GIL_RELEASED, 0)                                                                             \
    X(GIL_MUTEX, 1)                                                                                \
    X(SWITCH_MUTEX, 2)                                                                             \
    X(COND_WAITER, 3)                                                                              \
    X(SWITCH_WAITER, 4)                                                                            \
    X(COND_LOCK, 5)                                                                                \
    X(GIL_TIMEOUT, 6)                                                                              \
    X(PY_POOLS, 7)                                                                                 \
    X(GC_LINKS, 8)                                                                                 \
    X(FREELISTS, 9)                                                                                \
    X(PY_OBJECTS, 10)

enum {
#define CG_REPAIR_BIT(name, bit) CG_REPAIR_##name = 1 << (bit),
    CG_REPAIRS(CG_REPAIR_BIT)
#undef CG_REPAIR_BIT
};
/* cdef: end */

/* One dead task the repair looks at: a child whose thread group is gone
   (a zombie, or already reaped). */
struct cg_dead {
    pid_t pid;                 /* its tid (= pid) */
    char *tcb;                 /* its struct pthread */
    char *stack_lo, *stack_hi; /* its stack mapping */
    int slot;                  /* its allocator-guard slot, 0: none */
    uint32_t repairs;          /* out: CG_REPAIR_* attributed to it */
    void *gil_code;            /* out: it held the GIL: its innermost Python
                                  frame's code object (NULL: none), */
    int gil_lasti;             /* ... and instruction offset */
    int ref_dropped;           /* in: cg_gil_step_aside dropped its condvar
                                  group reference while it waited for its
                                  core dump */
};

struct cg_repair_cfg {
    int gil;                /* force-release the GIL / its mutexes */
    int condvar;            /* cancel dead waiters of the GIL's condvars */
    int interp;             /* mend the interpreter when the dead held the GIL */
    long cleanup_off;       /* struct pthread.cleanup (from the layout) */
    uintptr_t cond_cleanup; /* glibc's condvar-wait cleanup routine */
};

/* glibc 2.36's private record of a thread blocked in pthread_cond_wait
   (nptl/pthread_cond_wait.c, struct _condvar_cleanup_buffer): the argument
   of the cleanup routine the waiter pushes (struct pthread.cleanup) while it
   holds a reference on its condvar group.  cg_probe_condwait() checks this
   shape on a live waiter at start-up. */
struct cg_cond_cbuf {
    uint64_t wseq; /* its position << 1 | group index */
    void *cond;    /* pthread_cond_t * */
    void *mutex;   /* pthread_mutex_t * */
    int private_;
};

/* gilrepair.c.  Runs on the monitor thread, never takes the GIL.  Returns
   repairs that belong to no particular dead task. */
uint32_t cg_gil_repair(struct cg_dead *dead, int n, const struct cg_repair_cfg *cfg);
/* gilrepair.c, on the monitor thread, for a child whose crashing main task
   waits in its crash handler (for its core dump) and will never return to
   what it was doing: if it was blocked on one of the GIL's condvars, drop
   the group reference it holds there, so that no live signaller waits for
   it until it dies (each one would hold gil->mutex meanwhile, and every
   Python thread would wait for the dump).  d describes the task as for the
   repair; true if a reference was dropped (then the repair after its death
   must be told: cg_dead.ref_dropped). */
bool cg_gil_step_aside(struct cg_dead *d, const struct cg_repair_cfg *cfg);

/* interp.c: the interpreter after a death with the GIL held (slot: the
   dead task's, 0 if none; dead: its thread state), called while the GIL is
   still the dead task's (nobody runs Python): CG_REPAIR_* bits of what it
   did. */
struct _ts;
uint32_t cg_interp_after_gil_death(int slot, struct _ts *dead);

/* contexts.c, for interp.c: the allocator guard's Python object pools
   (pyalloc.c): abandon slot's (-ENOENT: no guard, or not in use); was p
   made in a pool since abandoned? */
int guard_py_abandon(int slot);
int guard_py_abandoned(const void *p);

/* The child's PyThreadState: made by the parent, bound by the child. */
struct _ts *cg_tstate_new(void);
void cg_tstate_bind(struct _ts *ts);

/* cdef: begin */
/* Facts for assumptions.py (takes the GIL itself). */
struct cg_gil_probe {
    unsigned long compiled_hex, running_hex;
    long runtime_size_compiled, runtime_size_elf;
    int locked; /* with the GIL held by the probe */
    int last_holder_is_me, tstate_current_is_me;
    int native_id_ok, thread_id_ok;
    int mutex_kind, switch_mutex_kind;
    int cond_wrefs_flags, switch_cond_wrefs_flags;
    long gil_offset, mutex_offset, cond_offset; /* for the report */
};
int cg_gil_probe(struct cg_gil_probe *out);

/* interp.c's facts for assumptions.py (takes the GIL itself). */
struct cg_interp_probe {
    int threshold[3], count[3]; /* generations[i], as compiled */
    int generation0_is_head;    /* gc.generation0 == &generations[0].head */
    int enabled, collecting;
    int young_links_ok; /* generation 0's links agree both ways */
    int free_lists_ok;  /* the free-list counts within bounds */
};
int cg_interp_probe(struct cg_interp_probe *out);

/* Async-signal-safe-ish: the Python stack of the calling thread, as
   faulthandler writes it. */
void cg_dump_py_stack(int fd);
/* Async-signal-safe: the calling thread's Python frames, raw (code object,
   instruction offset), innermost first; how many, and *more if the stack
   went on past max. */
int cg_record_py_stack(void **codes, int *lasti, int max, int *more);
/* In the container, without the GIL (each takes it): take or drop a
   reference on each recorded code object; write the frames as faulthandler
   would. */
void cg_hold_py_stack(void *const *codes, int n, int hold);
void cg_write_py_stack(void *const *codes, const int *lasti, int n, int more, int fd);
/* "name (file:line)" of one such frame into buf (size bytes); its length. */
int cg_frame_text(void *code, int lasti, char *buf, int size);

/* interp.c: the references a dead task's Python frames hold (tstate: its
   thread state, cg_child_tstate): known for certain, maybe, and its running
   frame's value stack (top: code, offset, words); see there. */
int cg_dead_frame_refs(void *tstate, uintptr_t *known, int nknown, uintptr_t *unknown, int nunknown,
                       uintptr_t *stack, int nstack, uintptr_t *top, int *counts);
/* interp.c: the collector's thread (collector.py) waits off the GIL until
   a collection is due (its generation; -1: woken), then runs it. */
int cg_gc_wait_due(int interval_us, int *wake);
long cg_gc_collect(void *collect, int generation);
/* cdef: end */

/* interp.c: read len bytes at addr into out without faulting (false where
   any is unmapped).  What a dead task left is read only so. */
#include <stddef.h>
bool cg_peek(const void *addr, void *out, size_t len);
#define PEEK(addr, var) cg_peek((addr), &(var), sizeof(var))

#endif
