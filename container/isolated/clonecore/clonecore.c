/*
 * clonecore.c - the C core of cloneguard's --isolated mode: the calls Python
 * makes (core.py).  core.h says which file does what.
 *
 * A "child" is a task made with clone3(CLONE_VM) and no CLONE_THREAD: its own
 * pid, signal dispositions and rlimits, but the container's address space.
 * glibc knows nothing of such a task, so the core gives it what
 * pthread_create would have: a TLS block with a struct pthread in it, a stack,
 * a robust-futex list, a locale.  Everything layout-dependent (offsets into
 * struct pthread, TLS offsets) comes from assumptions.py through struct
 * cg_layout; that module discovers each value and checks it against a live
 * thread before anything here runs.  x86_64 and glibc only.
 *
 * Threads and who may touch what:
 *   - The monitor thread (one, started by cg_start) performs every clone3,
 *     because PR_SET_PDEATHSIG fires when the *spawning thread* dies.  It
 *     waits on pidfds, reaps children and reports to Python through a pipe of
 *     fixed-size records.  It never takes the GIL.  It alone touches the child
 *     list (g_children) and cg_child.stop_reported.
 *   - Python threads call cg_spawn / cg_request_stop / cg_go / cg_release; cffi
 *     releases the GIL around each call.
 *   - A child runs child_main on its own stack and TLS, then the Python
 *     callable under PyGILState_Ensure, then leaves with a raw SYS_exit.
 *
 * After a death, before reaping, the monitor calls gilrepair.c to undo what
 * the dead task left in CPython's GIL (see there).  Crash reports come from
 * the child itself (on_crash, on its own sigaltstack).
 */
#include "core.h"
#include "clonecore.h"
#include "child.h"
#include "contexts.h"
#include "crash.h"
#include "herald.h"
#include "monitor.h"
#include "probes.h"

#include <errno.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/wait.h>
#include <unistd.h>

/* Set once by cg_start, before anything reads them; read-only afterwards,
   through the accessors below. */
static struct cg_layout g_layout;
static struct cg_config g_cfg;
static mallctl_fn g_mallctl;
static int g_started;

const struct cg_config *cg_cfg(void)
{
    return &g_cfg;
}

const struct cg_layout *cg_tcb_layout(void)
{
    return &g_layout;
}

mallctl_fn cg_mallctl(void)
{
    return g_mallctl;
}

/* ---------------------------------------------------------------------- */
/* The core.                                                               */

/* Start the core: its configuration, glibc's TLS allocator, the allocator
   guard when it is on, then the monitor thread.  *event_fd receives the read
   end of the event pipe, which Python owns (and closes after cg_stop). */
int cg_start(const struct cg_layout *layout, const struct cg_config *cfg, int *event_fd)
{
    if (g_started)
        return -EALREADY;
    g_cfg = *cfg;
    g_mallctl = find_mallctl();
    if (g_cfg.crash_report)
        crash_report_prepare();
    int r = tls_init();
    if (r < 0)
        return r;
    g_layout = *layout;
    if (g_cfg.alloc_guard && (r = guard_start()) < 0)
        return r;
    if ((r = monitor_start(event_fd)) < 0)
        return r;
    g_started = 1;
    return 0;
}

static void ahead_drop(void);

/* Stop the monitor: -EBUSY while any child is unreaped. */
int cg_stop(void)
{
    if (!g_started)
        return -EALREADY;
    int r = monitor_stop();
    if (r == 0) {
        g_started = 0;
        ahead_drop();
    }
    return r;
}

/* ---------------------------------------------------------------------- */
/* Children, from Python.                                                  */

static void forget_thread_state(PyThreadState *t);

/* What a child needs that does not depend on what it will run: its control
   block, its stack and signal stack (each with a PROT_NONE guard page below),
   and its PyThreadState.  cg_spawn takes the one made ahead for it (g_ahead)
   and makes the next after the clone, off the spawn's critical path: mmap,
   mprotect and the thread state's allocation are ~25 us of a cold spawn. */
static struct cg_child *g_ahead; /* atomic exchange; NULL: none */

static void block_free(struct cg_child *c)
{
    herald_forget(c);
    if (c->tstate)
        forget_thread_state(c->tstate);
    if (c->alt)
        munmap(c->alt, c->alt_len);
    if (c->map)
        munmap(c->map, c->map_len);
    free(c);
}

static struct cg_child *block_new(size_t stack_size)
{
    size_t page = (size_t)sysconf(_SC_PAGESIZE);
    struct cg_child *c = calloc(1, sizeof *c);
    if (!c)
        return NULL;
    c->stack_size = stack_size;
    c->map_len = stack_size + page;
    c->map = mmap(NULL, c->map_len, PROT_READ | PROT_WRITE,
                  MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE | MAP_STACK, -1, 0);
    c->alt_len = 64 * 1024 + page;
    c->alt = mmap(NULL, c->alt_len, PROT_READ | PROT_WRITE,
                  MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE | MAP_STACK, -1, 0);
    if (c->map == MAP_FAILED)
        c->map = NULL;
    if (c->alt == MAP_FAILED)
        c->alt = NULL;
    c->tstate = cg_tstate_new();
    if (!c->map || !c->alt || !c->tstate) {
        block_free(c);
        return NULL;
    }
    mprotect(c->map, page, PROT_NONE);
    mprotect(c->alt, page, PROT_NONE);
    return c;
}

static void ahead_refill(size_t stack_size)
{
    if (__atomic_load_n(&g_ahead, __ATOMIC_ACQUIRE))
        return;
    struct cg_child *b = block_new(stack_size), *none = NULL;
    if (b &&
        !__atomic_compare_exchange_n(&g_ahead, &none, b, false, __ATOMIC_ACQ_REL, __ATOMIC_ACQUIRE))
        block_free(b); /* another spawn refilled it first */
}

static void ahead_drop(void)
{
    struct cg_child *b = __atomic_exchange_n(&g_ahead, NULL, __ATOMIC_ACQ_REL);
    if (b)
        block_free(b);
}

int cg_spawn(void *target, uint64_t serial, size_t stack_size, int cgroup_fd, int flags,
             struct cg_child **out)
{
    if (!g_started)
        return -ESRCH;
    if (cg_self_stop_requested() >= 0) /* called from a child */
        return -EPERM;
    size_t page = (size_t)sysconf(_SC_PAGESIZE);
    stack_size = (stack_size + page - 1) & ~(page - 1);
    if (stack_size < 16 * page)
        return -EINVAL;

    struct cg_child *c = __atomic_exchange_n(&g_ahead, NULL, __ATOMIC_ACQ_REL);
    if (c && c->stack_size != stack_size) {
        block_free(c);
        c = NULL;
    }
    if (!c && !(c = block_new(stack_size)))
        return -ENOMEM;
    c->target = target;
    c->serial = serial;
    c->flags = flags;
    c->cgroup_fd = cgroup_fd;
    c->pidfd = -1;
    c->arena = -1;
    if (guard_active()) {
        c->ctx = ctx_take();
        c->tcb = c->ctx ? c->ctx->tcb : NULL;
        if (c->tcb) {
            tls_reset(c->tcb);
            guard_bind(c->ctx);
        }
    } else {
        c->tcb = tls_new();
    }
    int r = c->tcb ? monitor_spawn(c) : -ENOMEM;
    if (r < 0) {
        tls_give_back(c);
        block_free(c);
        return r;
    }
    *out = c;
    ahead_refill(stack_size);
    return 0;
}

/* Set the child's stop flag, then end its waits at the gate (it goes on to
   find the flag set); 1 if this call set the flag. */
int cg_request_stop(struct cg_child *c)
{
    int none = CG_STOP_NONE;
    int set = __atomic_compare_exchange_n(&c->stop_requested, &none, CG_STOP_PARENT, false,
                                          __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST);
    child_gate_post(c, 1);
    if (set)
        monitor_wake();
    return set;
}

/* One go for a child's next (or current) wait at its gate. */
int cg_go(struct cg_child *c)
{
    child_gate_post(c, 0);
    return 0;
}

/* Unlink and free a reaped child's PyThreadState (it was never current
   anywhere else).  A child killed inside Python leaves its tstate->cframe
   pointing into its stack: once that stack is unmapped, sys._current_frames()
   would crash, so this comes first.  Objects its frames referenced leak.  If
   the child died holding the GIL, the monitor released it before the death
   was reported: with gil_repair off this blocks forever. */
static void forget_thread_state(PyThreadState *t)
{
    PyGILState_STATE g = PyGILState_Ensure();
    PyThreadState_Clear(t);
    PyThreadState_Delete(t);
    PyGILState_Release(g);
}

/* The monitor reports a death before the dead child is reaped (monitor.c,
   reap): it is reaped here, once Python is done with it. */
static void reap_zombie(struct cg_child *c)
{
    siginfo_t gone;
    memset(&gone, 0, sizeof gone);
    /* ECHILD: something else in the container reaped it first. */
    waitid((idtype_t)P_PIDFD, (id_t)c->pidfd, &gone, WEXITED | __WALL | WNOHANG);
}

/* Reap and free what a dead child had: -EBUSY if it is not reported dead
   yet. */
int cg_release(struct cg_child *c)
{
    if (__atomic_load_n(&c->state, __ATOMIC_ACQUIRE) != CG_REAPED)
        return -EBUSY;
    reap_zombie(c);
    close(c->pidfd);
    tls_give_back(c);
    block_free(c);
    return 0;
}

/* Child c's Python thread state (reclaim.py reads a dead one's frames:
   cg_dead_frame_refs).  Valid until cg_release. */
void *cg_child_tstate(const struct cg_child *c)
{
    return c->tstate;
}

/* A reaped child whose Python state must stay where it is (the host keeps a
   crashed node's objects: destroying them could block on a lock the child
   held): its thread state and stacks stay allocated (its frames point into
   them); its TLS context goes back to the pool (or stays quarantined), or
   with hold_context stays the child's until cg_child_give_back, and its
   pidfd is closed.  -EBUSY if not reaped yet. */
int cg_abandon(struct cg_child *c, int hold_context)
{
    if (__atomic_load_n(&c->state, __ATOMIC_ACQUIRE) != CG_REAPED)
        return -EBUSY;
    herald_forget(c);
    if (c->ctx && !hold_context)
        tls_give_back(c);
    if (c->pidfd >= 0) {
        reap_zombie(c);
        close(c->pidfd);
    }
    c->pidfd = -1;
    return 0;
}
