/*
 * contexts.c - TLS blocks for children, and the allocator guard's contexts.
 *
 * glibc gives each pthread a TLS block with its struct pthread at the thread
 * pointer; a child gets one too, from glibc's own _dl_allocate_tls, filled in
 * here by the parent with what pthread_create would have set (offsets from
 * cg_tcb_layout()).  With the allocator guard (allocguard.c, preloaded), a TLS block
 * is bound to an allocator slot for good: the pair is a context (core.h),
 * pooled and reused by the next child unless its child died inside the
 * allocator.  Runs on container threads, never in a child.
 */
#include "core.h"
#include "contexts.h"
#include "clonecore.h"
#include "probes.h"
#include "sigsafe.h"

#include <asm/prctl.h>
#include <dlfcn.h>
#include <errno.h>
#include <pthread.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <unistd.h>

static void *(*dl_allocate_tls)(void *);
static void (*dl_deallocate_tls)(void *, bool);

/* The allocator guard's entry points (allocguard.h), when it is preloaded. */
static struct {
    cga_activate_fn activate;
    cga_slot_new_fn slot_new;
    cga_warm_fn warm;
    cga_slot_bind_fn slot_bind;
    cga_child_start_fn child_start;
    cga_slot_retire_fn slot_retire;
    cga_slot_stats_fn slot_stats;
    cga_py_stats_fn py_stats;
    cga_py_owner_fn py_owner;
    cga_py_active_fn py_active;
    cga_py_abandon_fn py_abandon;
    cga_py_abandoned_fn py_abandoned;
    cga_py_drain_fn py_drain;
    cga_slot_drain_fn slot_drain;
    cga_slot_of_fn slot_of;
    cga_slot_set_limit_fn slot_set_limit;
    cga_slot_memory_fn slot_memory;
    cga_stop_request_fn stop_request; /* optional: the rig's stop points */
    cga_dump_exclude_fn dump_exclude; /* optional: --core-dumps */
} G;

static pthread_mutex_t g_pool_lock = PTHREAD_MUTEX_INITIALIZER; /* container threads only */
static struct cg_ctx *g_pool; /* idle contexts, most recent first */
static void ctx_put(struct cg_ctx *x);

/* ---------------------------------------------------------------------- */
/* TLS blocks.                                                              */

int tls_init(void)
{
    dl_allocate_tls = (void *(*)(void *))dlvsym(RTLD_DEFAULT, "_dl_allocate_tls", "GLIBC_PRIVATE");
    dl_deallocate_tls =
        (void (*)(void *, bool))dlvsym(RTLD_DEFAULT, "_dl_deallocate_tls", "GLIBC_PRIVATE");
    return dl_allocate_tls && dl_deallocate_tls ? 0 : -ENOSYS;
}

/* What a child may leave behind in its struct pthread that the next child
   in the same TLS block must not inherit. */
void tls_reset(char *tcb)
{
    const struct cg_layout *L = cg_tcb_layout();
    /* Empty robust list: list points at the head itself. */
    AT(tcb, L->robust_head, void *) = tcb + L->robust_head;
    AT(tcb, L->robust_head + 8, long) = L->robust_futex_offset;
    AT(tcb, L->robust_head + 16, void *) = NULL;
    /* No pthread_cleanup record (one is left by a death in a condvar wait,
       and gilrepair.c reads it). */
    AT(tcb, L->cleanup, void *) = NULL;
}

char *tls_new(void)
{
    const struct cg_layout *L = cg_tcb_layout();
    char *tcb = dl_allocate_tls(NULL); /* struct pthread zeroed, dtv set */
    if (!tcb)
        return NULL;
    char *me = (char *)cg_thread_pointer();

    AT(tcb, L->tcb, void *) = tcb; /* THREAD_SELF reads these */
    AT(tcb, L->self, void *) = tcb;
    /* x86 catomic_* skip the lock prefix when this is 0: must be 1. */
    AT(tcb, L->multiple_threads, int) = 1;
    /* The canary only needs to be stable per task, but pointer_guard must
       equal every other thread's: mangled pointers (setjmp buffers, atexit
       and dl handlers) are shared. */
    AT(tcb, L->stack_guard, uintptr_t) = AT(me, L->stack_guard, uintptr_t);
    AT(tcb, L->pointer_guard, uintptr_t) = AT(me, L->pointer_guard, uintptr_t);
    /* Not on GL(dl_stack_used): an empty self-linked list keeps list_del
       (fork in a child) harmless. */
    AT(tcb, L->list, void *) = tcb + L->list;
    AT(tcb, L->list + 8, void *) = tcb + L->list;
    /* pthread_getspecific for keys < 32 goes through specific[0]. */
    AT(tcb, L->specific, void *) = tcb + L->specific_1stblock;
    /* rseq is not registered for the child: RSEQ_CPU_ID_REGISTRATION_FAILED
       makes sched_getcpu fall back to the syscall. */
    AT(tcb, L->rseq_cpu_id, int32_t) = -2;
    tls_reset(tcb);
    /* tid is written by the kernel (CLONE_{CHILD,PARENT}_SETTID). */
    return tcb;
}

/* The child's TLS block, after it ended or never started: back to the pool
   with its context, kept for good when it died inside the allocator, freed
   when there is no guard. */
void tls_give_back(struct cg_child *c)
{
    if (c->ctx) {
        if (c->retired & CGA_RETIRE_QUARANTINED) {
            free(c->ctx); /* the TLS block itself stays */
        } else {
            G.slot_retire(c->ctx->slot, c->ctx->tcb, 0); /* idle (again, if reaped) */
            ctx_put(c->ctx);
        }
        c->ctx = NULL;
    } else if (c->tcb) {
        dl_deallocate_tls(c->tcb, true);
    }
    c->tcb = NULL;
}

/* ---------------------------------------------------------------------- */
/* The allocator guard's contexts.                                         */

int guard_start(void)
{
    if (G.activate)
        return 0; /* one activation per process */
#define FIND(field, name) G.field = (void *)dlsym(RTLD_DEFAULT, name)
    FIND(activate, "cga_activate");
    FIND(slot_new, "cga_slot_new");
    FIND(warm, "cga_warm");
    FIND(slot_bind, "cga_slot_bind");
    FIND(child_start, "cga_child_start");
    FIND(slot_retire, "cga_slot_retire");
    FIND(slot_stats, "cga_slot_stats");
    FIND(py_stats, "cga_py_stats");
    FIND(py_owner, "cga_py_owner");
    FIND(py_active, "cga_py_active");
    FIND(py_abandon, "cga_py_abandon");
    FIND(py_abandoned, "cga_py_abandoned");
    FIND(py_drain, "cga_py_drain");
    FIND(slot_drain, "cga_slot_drain");
    FIND(slot_of, "cga_slot_of");
    FIND(slot_set_limit, "cga_slot_set_limit");
    FIND(slot_memory, "cga_slot_memory");
    FIND(stop_request, "cga_stop_request");
    FIND(dump_exclude, "cga_dump_exclude");
#undef FIND
    if (!G.activate || !G.slot_new || !G.warm || !G.slot_bind || !G.child_start || !G.slot_retire ||
        !G.slot_stats || !G.py_stats || !G.py_owner || !G.py_active || !G.py_abandon ||
        !G.py_abandoned || !G.py_drain || !G.slot_drain || !G.slot_of || !G.slot_set_limit ||
        !G.slot_memory) {
        memset(&G, 0, sizeof G);
        return -ENOENT; /* not preloaded */
    }
    int r = G.activate(getpid());
    if (r < 0 && r != -EALREADY) {
        memset(&G, 0, sizeof G);
        return r;
    }
    return 0;
}

/* Run cga_warm(slot) as the context's own task would: with its TLS block as
   this thread's, for the few calls that set up its allocator state.  All
   signals stay blocked meanwhile (no handler may run on a borrowed TLS);
   nothing here touches TLS itself across the switch. */
static __attribute__((noinline)) int ctx_warm(struct cg_ctx *x)
{
    sigset_t all, old;
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    uintptr_t mine = cg_thread_pointer();
    syscall(SYS_arch_prctl, ARCH_SET_FS, (unsigned long)x->tcb);
    int r = G.warm(x->slot);
    syscall(SYS_arch_prctl, ARCH_SET_FS, (unsigned long)mine);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    return r;
}

struct cg_ctx *ctx_take(void)
{
    pthread_mutex_lock(&g_pool_lock);
    struct cg_ctx *x = g_pool;
    if (x)
        g_pool = x->next;
    pthread_mutex_unlock(&g_pool_lock);
    if (x)
        return x;
    x = calloc(1, sizeof *x);
    if (!x)
        return NULL;
    x->tcb = tls_new();
    x->slot = x->tcb ? G.slot_new() : -ENOMEM;
    if (x->slot < 0 || ctx_warm(x) < 0) {
        /* A slot made and not warmed stays unused: never handed out. */
        if (x->tcb)
            dl_deallocate_tls(x->tcb, true);
        free(x);
        return NULL;
    }
    return x;
}

static void ctx_put(struct cg_ctx *x)
{
    pthread_mutex_lock(&g_pool_lock);
    x->next = g_pool;
    g_pool = x;
    pthread_mutex_unlock(&g_pool_lock);
}

/* What an allocator slot holds (allocguard.h); -ENOENT without the guard. */
int cg_alloc_slot_stats(int slot, struct cga_slot_stats *out)
{
    return G.slot_stats ? G.slot_stats(slot, out) : -ENOENT;
}

/* CPython's object allocator of a slot (pyalloc.c); -ENOENT without the guard. */
int cg_py_slot_stats(int slot, struct cga_py_stats *out)
{
    return G.py_stats ? G.py_stats(slot, out) : -ENOENT;
}

/* The slot whose process allocated Python object memory p; -1 if unknown. */
int guard_py_owner(const void *p)
{
    return G.py_owner ? G.py_owner(p) : -1;
}

int guard_py_abandon(int slot)
{
    return G.py_abandon && G.py_active && G.py_active() ? G.py_abandon(slot) : -ENOENT;
}

int guard_py_abandoned(const void *p)
{
    return G.py_abandoned ? G.py_abandoned(p) : 0;
}

/* A dead child's slot, whose context cg_abandon held back from the pool
   (so that no spawn has bound the slot since): the blocks handed to it
   freed now, by the caller, and its memory given back (a dead node's
   objects the container let go of: reclaim.py): its Python object pools'
   (pyalloc.c cga_py_drain, holding the GIL, taken here), then, under
   jemalloc, its arenas' (allocguard.c cga_slot_drain).  Then the context
   goes back to the pool.  How many blocks of each in counts (-1: not that
   kind: no guard, glibc, or a quarantined slot, which keeps what it was
   handed).  Without the guard a child has no context: nothing to do. */
void cg_child_give_back(struct cg_child *c, long *counts)
{
    counts[0] = counts[1] = -1;
    if (!c->ctx)
        return;
    if (!(c->retired & CGA_RETIRE_QUARANTINED)) {
        int slot = c->ctx->slot;
        if (G.py_active && G.py_active()) {
            PyGILState_STATE g = PyGILState_Ensure();
            long n = G.py_drain(slot);
            PyGILState_Release(g);
            counts[0] = n < 0 ? -1 : n;
        }
        long n = G.slot_drain(slot);
        counts[1] = n < 0 ? -1 : n;
    }
    tls_give_back(c);
}

/* Protection keys over node heaps (heapkeys.c): how many are in use, or
   -errno why not (-ENOENT: not asked for, or no guard).  Before
   guard_start too: the guard allocates them in its constructor. */
int cg_pkeys_in_use(int *keys, int max)
{
    cga_pkeys_fn f = (cga_pkeys_fn)dlsym(RTLD_DEFAULT, "cga_pkeys");
    return f ? f(keys, max) : -ENOENT;
}

/* The allocator slot child c runs in (0: none). */
int cg_child_slot(const struct cg_child *c)
{
    return c->ctx ? c->ctx->slot : 0;
}

/* Child c's memory budget from now on (0: none); -ENOENT without the guard. */
int cg_child_set_memory_limit(const struct cg_child *c, uint64_t bytes)
{
    if (!G.slot_set_limit || !c->ctx)
        return -ENOENT;
    return G.slot_set_limit(c->ctx->slot, bytes);
}

/* Child c's memory in use and budget (allocguard.c); -ENOENT without the guard. */
int cg_child_memory(const struct cg_child *c, struct cga_slot_memory *out)
{
    if (!G.slot_memory || !c->ctx)
        return -ENOENT;
    return G.slot_memory(c->ctx->slot, out);
}

/* The slot whose native heap range holds p; -1 if none (or no guard). */
int cg_alloc_slot_of(const void *p)
{
    return G.slot_of ? G.slot_of(p) : -1;
}

bool guard_active(void)
{
    return G.activate != NULL;
}

/* The calling container thread hands the slot to the child it spawns. */
void guard_bind(struct cg_ctx *x)
{
    G.slot_bind(x->slot);
}

/* In the child: threads it creates find its slot by its pid. */
void guard_child_start(void)
{
    G.child_start();
}

/* --core-dumps: leave the guard's untouched reserved memory out of the
   dumps written meanwhile (exclude 1), or put it back (0); 0 or -errno. */
int guard_dump_exclude(int exclude)
{
    return G.dump_exclude ? G.dump_exclude(exclude) : 0;
}

/* In the child: stop requests on signal sig (the test rig's stop points,
   stops.c); without the guard there is nowhere to stop, and the signal is
   ignored rather than left to end the process. */
void stop_requests_take(int sig)
{
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    if (G.stop_request) {
        sa.sa_sigaction = G.stop_request;
        sa.sa_flags = SA_SIGINFO | SA_RESTART;
    } else {
        sa.sa_handler = SIG_IGN;
    }
    sigemptyset(&sa.sa_mask);
    sigaction(sig, &sa, NULL);
}

/* Every task of the child is gone: CGA_RETIRE_* bits (allocguard.h): its
   slot quarantined (it died inside malloc, or faulted), its Python pools
   abandoned. */
int guard_retire(struct cg_ctx *x, bool faulted)
{
    return G.slot_retire(x->slot, x->tcb, faulted);
}

void guard_say_over_budget(struct cg_ctx *x, char *text, size_t cap)
{
    struct cga_slot_memory m;
    struct ss_buf o = {text, cap - 1, strlen(text)};
    if (o.n >= o.cap || G.slot_memory(x->slot, &m) != 0 || !m.over_asked)
        return;
    bool small = m.over_asked < MIB;
    ss_str(&o, "; out of memory: ");
    ss_ratio(&o, m.over_used, MIB, 1);
    ss_str(&o, " MiB in use, over its limit of ");
    ss_ratio(&o, m.limit, MIB, 1);
    ss_str(&o, " MiB (it asked for ");
    ss_ratio(&o, m.over_asked, small ? 1024 : MIB, small ? 0 : 1);
    ss_str(&o, small ? " KiB more)" : " MiB more)");
    ss_cstr(&o);
}
