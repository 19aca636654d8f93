/*
 * pyalloc.c - Python's object allocator, one per node process: part of the
 * allocator guard (allocguard.c), preloaded into an isolated container.
 *
 * CPython's own small-object allocator (pymalloc) keeps one set of pools
 * for the whole interpreter, guarded by the GIL only.  Every node process of
 * an isolated container allocates Python objects all the time, so a node
 * SIGKILLed inside pymalloc left its free lists or pool lists half-updated;
 * the GIL repair then handed the GIL to another process, whose next
 * allocation followed the torn list and the container died of SIGSEGV
 * (bench.random_kill, busy Python victim: about 1 kill in 270).
 *
 * This allocator serves CPython's MEM and OBJ domains (installed before
 * Python starts, below) with the guard's rule:
 *
 *     A node process's allocator state is touched only by that process.
 *
 * Each slot (allocguard.h: a node process, or slot 0, the container) owns
 * pools of one block size, carved from one reserved region, 16 KiB-aligned:
 * the pool header names its owner and the owner's *generation*.  A process
 * allocates only from its own pools and frees its own blocks into them.  A
 * block of another slot is pushed onto that slot's hand-over stack (its
 * first word links it; one CAS is the commit point) and freed by the owner
 * at its next allocation.  A process killed inside this allocator (its
 * calls are bracketed like the guard's: a TLS word for a node process's
 * main task, the slot's counter for its other threads) leaves only its own
 * pools torn: at retirement its generation is bumped and its pools are
 * abandoned for good (blocks in them stay valid while referenced; frees of
 * them are dropped and counted, and a pool whose last block is freed gives
 * its pages back), and the next process in that slot starts with fresh
 * pools.  Blocks over SMALL_MAX bytes go to malloc (the guard),
 * or with protection keys on to the slot's shared arena (heapkeys.c), as
 * does CPython's RAW domain then.
 *
 * Only the owner ever writes a pool; everyone reads pool headers.  Every
 * call of these domains is made holding the GIL (CPython's rule), so no
 * two run at once; the atomics are for the hand-over stack and the region's
 * bump pointer, which a death can leave at any instruction.
 *
 * The allocator is installed from a constructor, before CPython reads its
 * configuration: with PYTHONMALLOC set (debug hooks, pymalloc, malloc),
 * CPython installs that one over it, which cga_py_active() tells.
 * CLONEGUARD_PYALLOC=0 leaves CPython's own in place, for measurement.
 */
#define _GNU_SOURCE
#include <Python.h>

#include <dlfcn.h>
#include <errno.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>

#include "allocguard.h"
#include "guard_internal.h"

#define EXPORT __attribute__((visibility("default")))
#define likely(x) __builtin_expect(!!(x), 1)
#define unlikely(x) __builtin_expect(!!(x), 0)

#define POOL ((uintptr_t)16 << 10) /* bytes a pool, and its alignment */
#define ALIGN 16                   /* CPython's: every block 16-aligned */
#define SMALL_MAX 512              /* larger blocks: malloc */
#define NCLASSES (SMALL_MAX / ALIGN)
#define REGION ((size_t)64 << 30) /* reserved address space, all slots */
#define EMPTY_KEPT 16             /* empty pools an owner keeps paged in */

struct pool {
    uint16_t owner; /* slot */
    uint16_t gen;   /* owner's generation when made */
    uint16_t cls;   /* block size = (cls + 1) * ALIGN */
    uint16_t size;
    uint32_t used; /* blocks handed out */
    uint32_t pad;
    void *free;               /* freed blocks, linked */
    char *bump, *end;         /* never handed out yet */
    struct pool *next, *prev; /* in its owner's usable[cls] (or empty) */
};
#define HEADER (((sizeof(struct pool) + ALIGN - 1) / ALIGN) * ALIGN)
/* An empty pool gives back the pages past its first (madvise takes whole
   pages: the header's page stays, and with it three quarters go back). */
#define PAGE ((uintptr_t)4096)

struct owner {
    uint16_t gen;
    struct pool *usable[NCLASSES]; /* pools with a free block */
    struct pool *empty;            /* pools with none in use */
    unsigned nempty;
    _Atomic(void *) handed; /* blocks others freed for us */
    _Atomic long inside;    /* its tasks in here (but a bound main task) */
    _Atomic uint64_t pools, dropped, handed_total, abandoned;
    _Atomic long bytes; /* in use by its process (its blocks'
                           sizes; written holding the GIL) */
};

static struct owner owners[CGA_NSLOTS];
static char *g_base;
static _Atomic uintptr_t g_bump; /* offset of the next fresh pool */
static bool g_installed;
static PyMemAllocatorEx g_mine;

/* A bound main task's word, read only after its death (like the guard's). */
static __thread int t_py_inside __attribute__((tls_model("initial-exec")));
static long g_py_inside_off;

static inline void enter(int s)
{
    if (!s)
        return;
    if (cga_caller_bound()) {
        t_py_inside++;
        atomic_signal_fence(memory_order_seq_cst);
    } else {
        atomic_fetch_add_explicit(&owners[s].inside, 1, memory_order_seq_cst);
    }
}

static inline void leave(int s)
{
    if (!s)
        return;
    if (cga_caller_bound()) {
        atomic_signal_fence(memory_order_seq_cst);
        t_py_inside--;
    } else {
        atomic_fetch_sub_explicit(&owners[s].inside, 1, memory_order_seq_cst);
    }
}

static inline bool ours(const void *p)
{
    return (uintptr_t)p - (uintptr_t)g_base < REGION;
}

static inline struct pool *pool_of(const void *p)
{
    return (struct pool *)((uintptr_t)p & ~(POOL - 1));
}

static void unlink_pool(struct pool **head, struct pool *p)
{
    if (p->prev)
        p->prev->next = p->next;
    else
        *head = p->next;
    if (p->next)
        p->next->prev = p->prev;
    p->next = p->prev = NULL;
}

static void push_pool(struct pool **head, struct pool *p)
{
    p->prev = NULL;
    p->next = *head;
    if (*head)
        (*head)->prev = p;
    *head = p;
}

static struct pool *new_pool(int s, int cls)
{
    struct owner *o = &owners[s];
    struct pool *p = o->empty;
    if (p) {
        unlink_pool(&o->empty, p);
        o->nempty--;
    } else {
        uintptr_t off = atomic_fetch_add_explicit(&g_bump, POOL, memory_order_relaxed);
        if (off + POOL > REGION)
            return NULL;
        p = (struct pool *)(g_base + off);
        atomic_fetch_add_explicit(&o->pools, 1, memory_order_relaxed);
    }
    p->owner = (uint16_t)s;
    p->gen = o->gen;
    p->cls = (uint16_t)cls;
    p->size = (uint16_t)((cls + 1) * ALIGN);
    p->used = 0;
    p->free = NULL;
    p->bump = (char *)p + HEADER;
    p->end = (char *)p + POOL;
    push_pool(&o->usable[cls], p);
    return p;
}

/* Into its own pool: the caller is p's owner, inside. */
static inline void count(struct owner *o, long n)
{
    atomic_store_explicit(&o->bytes, atomic_load_explicit(&o->bytes, memory_order_relaxed) + n,
                          memory_order_relaxed);
}

static void put_back(struct owner *o, struct pool *p, void *b)
{
    bool was_full = p->free == NULL && p->bump + p->size > p->end;
    count(o, -(long)p->size);
    *(void **)b = p->free;
    p->free = b;
    p->used--;
    if (was_full)
        push_pool(&o->usable[p->cls], p);
    if (p->used == 0) {
        unlink_pool(&o->usable[p->cls], p);
        push_pool(&o->empty, p);
        if (++o->nempty > EMPTY_KEPT) /* keep the address (and header), give the pages back */
            madvise((char *)p + PAGE, POOL - PAGE, MADV_DONTNEED);
    }
}

/* The blocks handed to o, into its pools; how many (the rest were of
   abandoned pools: dropped). */
static long drain(struct owner *o)
{
    long n = 0;
    void *b = atomic_exchange_explicit(&o->handed, NULL, memory_order_acquire);
    while (b) {
        void *next = *(void **)b;
        struct pool *p = pool_of(b);
        if (p->gen == o->gen) {
            put_back(o, p, b);
            n++;
        } else {
            atomic_fetch_add_explicit(&o->dropped, 1, memory_order_relaxed);
        }
        b = next;
    }
    return n;
}

static void *small_alloc(size_t n)
{
    int s = cga_caller_slot();
    struct owner *o = &owners[s];
    int cls = (int)((n - 1) / ALIGN);
    if (unlikely(!o->usable[cls])) /* a pool more: within its budget? */
        cga_within_budget(s, POOL);
    enter(s);
    if (unlikely(atomic_load_explicit(&o->handed, memory_order_relaxed) != NULL))
        drain(o);
    struct pool *p = o->usable[cls];
    if (unlikely(!p) && !(p = new_pool(s, cls))) {
        leave(s);
        return NULL;
    }
    void *b = p->free;
    if (b)
        p->free = *(void **)b;
    else {
        b = p->bump;
        p->bump += p->size;
    }
    cga_stop_point(s, CGA_STOP_PY_ALLOCATION); /* the pool half-updated */
    p->used++;
    count(o, p->size);
    if (p->free == NULL && p->bump + p->size > p->end)
        unlink_pool(&o->usable[cls], p); /* full */
    leave(s);
    return b;
}

static void small_free(void *b)
{
    struct pool *p = pool_of(b);
    int s = cga_caller_slot();
    struct owner *to = &owners[p->owner];
    if (p->gen != to->gen) { /* an abandoned pool: never written again but for its count */
        atomic_fetch_add_explicit(&to->dropped, 1, memory_order_relaxed);
        /* Its last block freed: all its pages go back, the header's too
           (nothing reads it again: a header is read only to free or
           reallocate a block of its pool).  The address stays reserved.
           A process killed anywhere in here never left a pool's count below
           its blocks in use (small_alloc counts a block before returning
           it, put_back frees it before uncounting it), so 0 means none is
           referenced. */
        if (__atomic_sub_fetch(&p->used, 1, __ATOMIC_RELAXED) == 0)
            madvise(p, POOL, MADV_DONTNEED);
        return;
    }
    if (p->owner == s) {
        enter(s);
        put_back(to, p, b);
        leave(s);
        return;
    }
    void *head = atomic_load_explicit(&to->handed, memory_order_relaxed);
    do
        *(void **)b = head;
    while (!atomic_compare_exchange_weak_explicit(&to->handed, &head, b, memory_order_release,
                                                  memory_order_relaxed));
    atomic_fetch_add_explicit(&to->handed_total, 1, memory_order_relaxed);
}

static void *py_malloc(void *ctx, size_t n)
{
    (void)ctx;
    if (n == 0)
        n = 1;
    return n <= SMALL_MAX ? small_alloc(n) : cga_shared_alloc(n, false);
}

static void *py_calloc(void *ctx, size_t n, size_t size)
{
    (void)ctx;
    size_t total;
    if (__builtin_mul_overflow(n, size, &total))
        return NULL;
    if (total == 0 || total > SMALL_MAX)
        return cga_shared_alloc(total ? total : 1, true);
    void *b = small_alloc(total);
    if (b)
        memset(b, 0, total);
    return b;
}

static void py_free(void *ctx, void *b)
{
    (void)ctx;
    if (!b)
        return;
    if (ours(b))
        small_free(b);
    else
        free(b);
}

static void *py_realloc(void *ctx, void *b, size_t n)
{
    if (!b)
        return py_malloc(ctx, n);
    if (n == 0)
        n = 1;
    if (!ours(b))
        return cga_shared_realloc(b, n); /* malloc'd: stays malloc'd */
    size_t have = pool_of(b)->size;
    if (n <= have && 4 * n > 3 * have)
        return b; /* fits well enough where it is */
    void *q = py_malloc(ctx, n);
    if (q) {
        memcpy(q, b, have < n ? have : n);
        small_free(b);
    }
    return q;
}

/* CPython's RAW domain, with protection keys (heapkeys.c): any thread,
   GIL or not; its blocks (thread states and their links, among others)
   are written by every node process. */
static void *raw_malloc(void *ctx, size_t n)
{
    (void)ctx;
    return cga_shared_alloc(n, false);
}

static void *raw_calloc(void *ctx, size_t n, size_t size)
{
    (void)ctx;
    size_t total;
    return __builtin_mul_overflow(n, size, &total) ? NULL : cga_shared_alloc(total, true);
}

static void *raw_realloc(void *ctx, void *b, size_t n)
{
    (void)ctx;
    return cga_shared_realloc(b, n);
}

static void raw_free(void *ctx, void *b)
{
    (void)ctx;
    free(b);
}

typedef void (*set_allocator_fn)(PyMemAllocatorDomain, PyMemAllocatorEx *);
typedef void (*get_allocator_fn)(PyMemAllocatorDomain, PyMemAllocatorEx *);
static get_allocator_fn g_get_allocator;

__attribute__((constructor)) static void install(void)
{
    const char *want = getenv("CLONEGUARD_PYALLOC");
    if (want && strcmp(want, "0") == 0)
        return;
    /* Looked up, not linked: a process that is not CPython has none. */
    set_allocator_fn set = (set_allocator_fn)dlsym(RTLD_DEFAULT, "PyMem_SetAllocator");
    g_get_allocator = (get_allocator_fn)dlsym(RTLD_DEFAULT, "PyMem_GetAllocator");
    if (!set || !g_get_allocator)
        return;
    void *r = mmap(NULL, REGION + POOL, PROT_READ | PROT_WRITE,
                   MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE, -1, 0);
    if (r == MAP_FAILED)
        return;
    g_base = (char *)(((uintptr_t)r + POOL - 1) & ~(POOL - 1));
    uintptr_t tp;
    __asm__("mov %%fs:0, %0" : "=r"(tp));
    g_py_inside_off = (long)((uintptr_t)&t_py_inside - tp);
    g_mine = (PyMemAllocatorEx){NULL, py_malloc, py_calloc, py_realloc, py_free};
    set(PYMEM_DOMAIN_MEM, &g_mine);
    set(PYMEM_DOMAIN_OBJ, &g_mine);
    if (hk_enabled()) { /* thread states, ...: shared too */
        static PyMemAllocatorEx raw = {NULL, raw_malloc, raw_calloc, raw_realloc, raw_free};
        set(PYMEM_DOMAIN_RAW, &raw);
    }
    g_installed = true;
}

/* ---------------------------------------------------------------------- */
/* For the guard and the clone core.                                       */

/* Every pool of slot s, abandoned: its blocks stay where they are (valid
   while referenced), none is handed out or freed into again, and frees of
   them are dropped; the slot starts a new generation with no pool.  Only
   while s's process cannot run: it is dead (or stopped) and nobody else
   ever writes its state. */
static void new_generation(struct owner *o)
{
    o->gen++;
    memset(o->usable, 0, sizeof o->usable);
    o->empty = NULL;
    o->nempty = 0;
    atomic_store(&o->handed, NULL); /* blocks of abandoned pools: dropped */
}

static void abandon(struct owner *o)
{
    new_generation(o);
    atomic_fetch_add(&o->abandoned, 1);
}

/* The slot whose process is gone: 1 if it died inside this allocator (its
   pools are abandoned now: a new generation starts empty), else 0. */
int py_slot_retire(int s, char *tcb)
{
    if (!g_installed)
        return 0;
    struct owner *o = &owners[s];
    bool inside =
        atomic_load(&o->inside) != 0 || (tcb && *(volatile int *)(tcb + g_py_inside_off) != 0);
    atomic_store(&o->inside, 0);
    if (tcb)
        *(volatile int *)(tcb + g_py_inside_off) = 0;
    if (!inside)
        return 0;
    abandon(o);
    return 1;
}

/* Slot s's process died holding the GIL, maybe half-way through building
   or changing objects of its own: its pools are abandoned, so that what it
   made can be told apart (cga_py_abandoned) from what the next process in
   that slot makes.  0, or -EINVAL. */
EXPORT int cga_py_abandon(int s)
{
    if (!g_installed || s <= 0 || s >= CGA_NSLOTS)
        return -EINVAL;
    abandon(&owners[s]);
    return 0;
}

/* Slot s, idle (its process is gone, and no other may take the slot
   meanwhile: contexts.c holds its context), has the blocks others freed
   for it freed into its pools now, by the caller, holding the GIL (the
   pools are written only so): a dead node's objects the container let go
   of (reclaim.py).  Then its pools are abandoned, as after a death inside
   here, so that the empty ones give back all their pages, header and all
   (an empty pool the slot kept for reuse keeps its header page: a quarter
   of it), and the rest theirs when their last block is freed
   (small_free); the next process in the slot starts with fresh pools.
   How many blocks were freed, or -EINVAL. */
EXPORT long cga_py_drain(int s)
{
    if (!g_installed || s <= 0 || s >= CGA_NSLOTS)
        return -EINVAL;
    struct owner *o = &owners[s];
    long n = drain(o);
    struct pool *empty = o->empty;
    new_generation(o);
    while (empty) {
        struct pool *next = empty->next; /* read before its pages go */
        madvise(empty, POOL, MADV_DONTNEED);
        empty = next;
    }
    return n;
}

/* Was block p (any pointer into it) made by this allocator in a pool since
   abandoned? */
EXPORT int cga_py_abandoned(const void *p)
{
    if (!g_installed || !ours(p))
        return 0;
    const struct pool *pl = pool_of(p);
    return pl->gen != owners[pl->owner].gen;
}

/* The slot that owns block p, allocated by this allocator; -1 if not ours. */
EXPORT int cga_py_owner(const void *p)
{
    return g_installed && ours(p) ? pool_of(p)->owner : -1;
}

/* Is this allocator serving CPython's object domain (not replaced by
   PYTHONMALLOC, not turned off)? */
EXPORT int cga_py_active(void)
{
    if (!g_installed)
        return 0;
    PyMemAllocatorEx now;
    g_get_allocator(PYMEM_DOMAIN_OBJ, &now);
    return now.malloc == py_malloc;
}

/* --core-dumps (allocguard.c cga_dump_exclude): the region's never-used tail, past the
   last pool handed out, left out of a dump while one is written
   (MADV_DONTDUMP: gdb skips it) and given back after.  Without it a dump
   writes 64 GiB of reserved, untouched address space out as zeros.  A pool
   handed out meanwhile is left out of that one dump. */
HIDDEN int py_dump_tail(int exclude)
{
    if (!g_base)
        return 0;
    uintptr_t used = exclude ? atomic_load(&g_bump) : 0;
    if (used >= REGION)
        return 0;
    return madvise(g_base + used, REGION - used, exclude ? MADV_DONTDUMP : MADV_DODUMP) ? -errno
                                                                                        : 0;
}

EXPORT int cga_py_stats(int s, struct cga_py_stats *out)
{
    if (s < 0 || s >= CGA_NSLOTS)
        return -EINVAL;
    struct owner *o = &owners[s];
    out->generation = o->gen;
    out->pools = atomic_load(&o->pools);
    out->handed = atomic_load(&o->handed_total);
    out->dropped = atomic_load(&o->dropped);
    out->abandoned = atomic_load(&o->abandoned);
    return 0;
}

/* Bytes of Python's small objects slot s's process has in use (the guard's
   memory in use, allocguard.c). */
HIDDEN long py_slot_bytes(int s)
{
    return atomic_load_explicit(&owners[s].bytes, memory_order_relaxed);
}

/* A new process in slot s: its count starts from nothing. */
HIDDEN void py_slot_begin(int s)
{
    atomic_store(&owners[s].bytes, 0);
}
