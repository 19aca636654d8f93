/*
 * allocguard.c - the allocator guard of cloneguard's --isolated mode.
 *
 * A malloc interposer, preloaded (LD_PRELOAD, before jemalloc if jemalloc is
 * used) into an isolated container.  Its one rule:
 *
 *     A node process's allocator state is touched only by that process.
 *
 * Every node process (a "slot") allocates from arenas nobody else allocates
 * from.  A block freed by anyone but its owner is never freed into the
 * owner's arena: it is pushed onto the owner's hand-over stack (one CAS, the
 * commit point), and the owner frees it into its arena at its next malloc or
 * free.  So when a node process is SIGKILLed inside malloc, holding its
 * arena's locks with its arena half-updated, no living task is ever inside,
 * or waiting for, that arena: the container marks it quarantined and never
 * uses it again; blocks handed to it afterwards stay on its stack (leaked,
 * counted).  A process that ended outside the allocator leaves a consistent
 * arena, which the next node process in that slot reuses, draining its stack.
 *
 * Whether a process died inside the allocator is known exactly: every call
 * a node process makes into the allocator is bracketed by a counter the
 * monitor reads after the death: a plain word in the TLS of the process's
 * main task (t_inside: the main task does nearly all the allocating), an
 * atomic counter of its slot (live[s].inside) for threads it created.
 *
 * Which arena owns a block (owner_of):
 *   jemalloc  each slot's arena is created by the container with extent hooks
 *             (below) that carve its memory out of a VA range reserved for
 *             that slot: the owner is arithmetic on the address.
 *   glibc     a chunk's header says mmapped (no arena: munmap takes no lock),
 *             main arena (the container's), or non-main; a non-main chunk's
 *             arena is the first word of its 64 MiB-aligned heap.  Arenas are
 *             mapped to slots as each thread learns its own (owners[]).
 *
 * A slot has two arenas (the split): the blocks the ROS stack and
 * the interpreter ask for come from its shared arena, those of the node's
 * own code from its own, so a node that tears its own blocks does not tear
 * the structures every task walks.  glibc chooses an arena per thread: the
 * guard swaps the two words of glibc's per-thread state (glibc_swap) for
 * each such call.
 *
 * Slot 0 is the container: its threads never die alone, so they free each
 * other's blocks directly, as the allocator does without us.  Threads a node
 * process creates (Fast DDS's) belong to its slot: they die with it.
 *
 * Before cga_activate() the guard passes everything straight through, so the
 * process starts as it would without it.  Layout facts (glibc 2.36 x86_64,
 * jemalloc 5.x public API) are checked at start-up by assumptions.py through
 * cga_probe_glibc and the backend name.  The data structures and the reasons
 * are in container/isolated/README.md.
 */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <errno.h>
#include <fcntl.h>
#include <link.h>
#include <malloc.h> /* memalign, pvalloc, malloc_usable_size */
#include <pthread.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <unistd.h>

#include "allocguard.h"
#include "guard_internal.h"

#define EXPORT __attribute__((visibility("default")))
#define likely(x) __builtin_expect(!!(x), 1)
#define unlikely(x) __builtin_expect(!!(x), 0)

/* ---------------------------------------------------------------------- */
/* The allocators underneath.                                              */

/* glibc's own entry points (exported by libc for exactly this use). */
extern void *__libc_malloc(size_t);
extern void __libc_free(void *);
extern void *__libc_calloc(size_t, size_t);
extern void *__libc_realloc(void *, size_t);
extern void *__libc_memalign(size_t, size_t);

/* jemalloc's non-standard API: bound to jemalloc when it is preloaded after
   us, NULL otherwise (weak).  Its malloc/free are shadowed by ours; these
   names are not. */
extern void *mallocx(size_t, int) __attribute__((weak));
extern void *rallocx(void *, size_t, int) __attribute__((weak));
extern void dallocx(void *, int) __attribute__((weak));
extern size_t sallocx(const void *, int) __attribute__((weak));
extern size_t nallocx(size_t, int) __attribute__((weak));
extern int mallctl(const char *, void *, size_t *, void *, size_t) __attribute__((weak));

/* jemalloc underneath?  A link-time fact: the weak reference is bound when
   jemalloc is loaded, before any code runs. */
#define g_je (mallocx != NULL)

/* jemalloc's own malloc and friends (its fast paths), found with
   dlsym(RTLD_NEXT) by cga_activate; until then the *x API serves. */
static struct {
    void *(*malloc)(size_t);
    void (*free)(void *);
    void *(*calloc)(size_t, size_t);
    void *(*realloc)(void *, size_t);
} je_real;

/* jemalloc's public flag encodings (jemalloc.h, man jemalloc: MALLOCX_*). */
#define JE_ZERO 0x40
#define JE_LG_ALIGN(la) ((int)(la))
#define JE_ARENA(a) ((((int)(a)) + 1) << 20)
#define JE_TCACHE(tc) (((int)(tc) + 2) << 8) /* MALLOCX_TCACHE(tc): an explicit cache */
#define JE_TCACHE_NONE JE_TCACHE(-1)         /* MALLOCX_TCACHE_NONE */

/* jemalloc's extent hook table (public ABI: man jemalloc, "arena.<i>.extent_hooks"). */
typedef struct je_hooks je_hooks;
struct je_hooks {
    void *(*alloc)(je_hooks *, void *, size_t, size_t, bool *, bool *, unsigned);
    bool (*dalloc)(je_hooks *, void *, size_t, bool, unsigned);
    void (*destroy)(je_hooks *, void *, size_t, bool, unsigned);
    bool (*commit)(je_hooks *, void *, size_t, size_t, size_t, unsigned);
    bool (*decommit)(je_hooks *, void *, size_t, size_t, size_t, unsigned);
    bool (*purge_lazy)(je_hooks *, void *, size_t, size_t, size_t, unsigned);
    bool (*purge_forced)(je_hooks *, void *, size_t, size_t, size_t, unsigned);
    bool (*split)(je_hooks *, void *, size_t, size_t, size_t, bool, unsigned);
    bool (*merge)(je_hooks *, void *, size_t, void *, size_t, bool, unsigned);
};

/* glibc 2.36 malloc, x86_64 (malloc/malloc.c, malloc/arena.c): the chunk
   size word just below a block carries IS_MMAPPED and NON_MAIN_ARENA; a
   non-main arena's heaps are HEAP_MAX_SIZE-aligned and begin with a
   heap_info whose first member is the arena.  Checked by cga_probe_glibc. */
#define GLIBC_IS_MMAPPED 0x2u
#define GLIBC_NON_MAIN_ARENA 0x4u
#define GLIBC_HEAP_MAX ((uintptr_t)64 << 20)
#define GLIBC_PROBE_SIZE 2048 /* above the tcache sizes: from the arena */
/* glibc keeps a thread's malloc state in two words of libc's static TLS
   (malloc/malloc.c, malloc/arena.c): thread_arena, the arena it allocates
   from, and tcache, its cache, a tcache_perthread_struct (64 two-byte counts
   and 64 entry pointers: a chunk of 656 bytes).  Their offsets from the
   thread pointer are found at activation (find_glibc_tls) and checked again
   for each context (glibc_warm_shared). */
#define GLIBC_TCACHE_CHUNK 656

/* ---------------------------------------------------------------------- */
/* State.                                                                  */

#define NSLOTS CGA_NSLOTS /* 0: the container; 1..: node processes */
#define SLOT_SHIFT 34     /* jemalloc: 16 GiB of address space a slot */
#define NOWNERS 8192      /* glibc: arenas (M_ARENA_MAX is 4096) */

/* An arena's hooks and the address range they carve from (jemalloc hands
   &h back to each hook). */
struct slot_hooks {
    je_hooks h;
    uintptr_t base, limit;
    _Atomic uintptr_t *bump; /* carved up to here (in live[]) */
};

/* jemalloc: a slot's range is two halves (the split): its own arena's and
   its shared arena's; with protection keys (heapkeys.c) the first is
   tagged with the slot's key, the second not. */
#define HALF_SHIFT (SLOT_SHIFT - 1)

struct slot {
    _Atomic int state;       /* CGA_* */
    unsigned arena;          /* jemalloc: the arena made for it */
    struct slot_hooks hooks; /* ... and its range */
    unsigned shared_arena;   /* jemalloc: for the stack's blocks (the split) */
    struct slot_hooks shared_hooks;
    _Atomic uint64_t main_allocs; /* glibc: blocks it got from the main
                                     arena (should stay 0: see
                                     container/allocator.py) */
    _Atomic uint64_t limit;       /* its memory budget in bytes, 0: none
                                     (here, under the container's key:
                                     no node can raise its own) */
};

/* An owner of blocks: who frees them into their arena.  jemalloc: owner i
   is slot i.  glibc: owner i (i > 0) is one arena (key), attributed to the
   slot whose thread last attached to it; owner 0 is the container's main
   arena and every arena of slot 0. */
struct owner {
    _Atomic(void *) key; /* glibc: the arena */
    _Atomic int slot;
    _Atomic(void *) stack;   /* blocks handed over, linked through
                                their first word */
    _Atomic(void *) held;    /* the small ones its last drain took off the
                                stack, freed at its next (HANDED_MARK) */
    _Atomic uint64_t handed; /* blocks pushed so far */
};

/* What a slot's own tasks write as they allocate, apart from struct slot so
   that the tables below can be under the container's key (heapkeys.c):
   writing that key's pages costs a PKRU switch each way, too dear on every
   malloc.  A wild write here can mislead the guard about one slot (its
   count inside, its pid, how far its ranges are carved), not redirect it. */
struct slot_live {
    _Atomic int pid;                        /* the process bound to it */
    _Atomic long inside;                    /* its tasks inside the allocator now */
    _Atomic uintptr_t bump, shared_bump;    /* jemalloc: its ranges carved so far */
    _Atomic long bytes;                     /* in use: its other threads' blocks and
                                               its mmapped ones (memory in use) */
    _Atomic(_Atomic long *) main_bytes;     /* its main task's own count (t_bytes) */
    _Atomic uint64_t over_used, over_asked; /* it went over its budget: what
                                          it had and what it asked for */
};

/* The guard's tables: written by container threads, and by node processes
   only where hk_open brackets the store (handing a block over, draining).
   Page-aligned and page-sized, so that with keys they alone are under the
   container's key (hk_tag_tables). */
static struct __attribute__((aligned(4096))) tables {
    struct slot slots[NSLOTS];
    struct owner owners[NOWNERS];
} g_tables;
#define slots g_tables.slots
#define owners g_tables.owners
static struct slot_live live[NSLOTS];
static _Atomic int g_active;
static int g_container_pid;
static uintptr_t g_region, g_region_len; /* jemalloc: slots 1.. carve from here */
static int g_nslots = NSLOTS;
/* The split: a node process's main task keeps the blocks the ROS stack and
   the interpreter ask for (hk_shared_caller says which) in an arena of its
   own, its shared arena, apart from those of the node's own code.  Those
   blocks are what other tasks walk (the shared participant's entity lists,
   the interpreter's objects): a node that overflows a block of its own, or
   frees one twice, tears its own arena, not them.  Always on once the guard
   is active, on both backends: jemalloc's slot range is two halves, the
   shared arena's the upper; under glibc, activation refuses unless glibc's
   per-thread malloc state was found (find_glibc_tls).  With protection keys
   the own half is keyed and the shared one not (heapkeys.c). */
static bool g_keys; /* protection keys on (heapkeys.c) */
/* glibc: thread_arena's and tcache's offsets from the thread pointer. */
static long g_tls_arena, g_tls_tcache;
static size_t g_page = 4096;
static size_t (*glibc_usable_size)(void *);

/* Per task: slot + 1 (0: not known yet), and which owner's stack it drains.
   t_bound: this is a node process's main task, whose allocator state the
   container set up (cga_warm): t_inside brackets its calls, and under
   jemalloc its thread arena is the slot's. */
static __thread int t_slot1 __attribute__((tls_model("initial-exec")));
static __thread int t_owner __attribute__((tls_model("initial-exec")));
static __thread int t_bound __attribute__((tls_model("initial-exec")));
static __thread int t_inside __attribute__((tls_model("initial-exec")));
static __thread void *t_arena __attribute__((tls_model("initial-exec"))); /* glibc: its own */
/* glibc, a bound main task with the split: its shared arena, that arena's
   cache, and its owner index. */
static __thread void *t_sh_arena __attribute__((tls_model("initial-exec")));
static __thread void *t_sh_tcache __attribute__((tls_model("initial-exec")));
static __thread int t_sh_owner __attribute__((tls_model("initial-exec")));
/* jemalloc, a bound main task: the explicit cache of its shared arena
   (tcache.create, made in cga_warm) + 1; 0: none (no cache: its other
   threads).  Only shared blocks ever enter it, so it never serves a shared
   block to a native malloc nor the reverse, as the thread cache would. */
static __thread unsigned t_sh_cache1 __attribute__((tls_model("initial-exec")));
/* A bound main task's bytes in use (memory in use, below): it alone writes
   it, the rest of its slot and the container read it. */
static __thread _Atomic long t_bytes __attribute__((tls_model("initial-exec")));
static long g_inside_off; /* &t_inside - thread pointer */

/* ---------------------------------------------------------------------- */
/* Owners.                                                                 */

static int glibc_arena_owner(void *arena) /* 0 if not known */
{
    uintptr_t h = ((uintptr_t)arena >> 12) * 0x9e3779b97f4a7c15ull;
    for (int n = 0; n < NOWNERS - 1; n++) {
        int i = 1 + (int)((h + (uintptr_t)n) % (NOWNERS - 1));
        void *k = atomic_load_explicit(&owners[i].key, memory_order_acquire);
        if (k == arena)
            return i;
        if (!k)
            return 0;
    }
    return 0;
}

static int glibc_arena_claim(void *arena, int slot)
{
    uintptr_t h = ((uintptr_t)arena >> 12) * 0x9e3779b97f4a7c15ull;
    for (int n = 0; n < NOWNERS - 1; n++) {
        int i = 1 + (int)((h + (uintptr_t)n) % (NOWNERS - 1));
        void *k = atomic_load_explicit(&owners[i].key, memory_order_acquire);
        if (!k && atomic_compare_exchange_strong(&owners[i].key, &k, arena))
            k = arena;
        if (k == arena) {
            atomic_store_explicit(&owners[i].slot, slot, memory_order_release);
            return i;
        }
    }
    return 0; /* table full: counted as the container's */
}

static void *glibc_arena_of(void *p) /* NULL: main arena or mmapped */
{
    size_t head = ((size_t *)p)[-1];
    if ((head & GLIBC_IS_MMAPPED) || !(head & GLIBC_NON_MAIN_ARENA))
        return NULL;
    return *(void **)((uintptr_t)p & ~(GLIBC_HEAP_MAX - 1));
}

/* The owner of block p: an owners[] index, or -1 if no arena needs to be
   entered to free it (a glibc mmapped chunk). */
static inline int owner_of(void *p)
{
    if (g_je) {
        uintptr_t off = (uintptr_t)p - g_region;
        return off < g_region_len ? 1 + (int)(off >> SLOT_SHIFT) : 0;
    }
    if (((size_t *)p)[-1] & GLIBC_IS_MMAPPED)
        return -1;
    void *arena = glibc_arena_of(p);
    if (arena && arena == t_arena)
        return t_owner; /* its own arena: no table lookup */
    if (arena && arena == t_sh_arena)
        return t_sh_owner;
    return arena ? glibc_arena_owner(arena) : 0;
}

/* Does the calling task have a shared arena?  Every task of a node
   process under jemalloc (its slot's); under glibc its main task. */
static inline bool has_shared(void)
{
    return g_je || t_sh_arena;
}

/* Is p, of owner o (owner_of(p)), a shared block: in some slot's shared
   half (jemalloc), or in the calling task's shared arena (glibc: the only
   one it frees into)? */
static inline bool shared_block(const void *p, int o)
{
    if (!g_je)
        return t_sh_owner && o == t_sh_owner;
    uintptr_t off = (uintptr_t)p - g_region;
    return off < g_region_len && ((off >> HALF_SHIFT) & 1);
}

static inline bool in_shared(void *p)
{
    return shared_block(p, g_je || !t_sh_owner ? 0 : owner_of(p));
}

/* glibc: run one call of glibc's malloc family on the task's shared arena
   and its cache, by swapping the two words of glibc's per-thread state (a
   free must swap the cache too: glibc caches a freed block in the calling
   thread's cache, whatever its arena). */
struct glibc_state {
    void *arena, *tcache;
};

static inline void **tls_word(long off)
{
    uintptr_t tp;
    __asm__("mov %%fs:0, %0" : "=r"(tp));
    return (void **)(tp + (uintptr_t)off);
}

static inline struct glibc_state glibc_swap(struct glibc_state to)
{
    void **a = tls_word(g_tls_arena), **c = tls_word(g_tls_tcache);
    struct glibc_state was = {*a, *c};
    *a = to.arena;
    *c = to.tcache;
    atomic_signal_fence(memory_order_seq_cst);
    return was;
}

#define ON_SHARED_ARENA(statement)                                                                 \
    do {                                                                                           \
        struct glibc_state own_ = glibc_swap((struct glibc_state){t_sh_arena, t_sh_tcache});       \
        statement;                                                                                 \
        glibc_swap(own_);                                                                          \
    } while (0)

static inline int owner_slot(int o)
{
    return o <= 0 ? 0 : atomic_load_explicit(&owners[o].slot, memory_order_acquire);
}

/* ---------------------------------------------------------------------- */
/* The backend calls, for the calling task's slot.                        */

/* jemalloc: a bound main task's (or the container's) arena is its thread
   arena already; another thread of a node process names its slot's. */
static inline int je_flags(int slot)
{
    return slot && !t_bound ? JE_ARENA(slots[slot].arena) : 0;
}

/* The cache a shared block goes through: the task's explicit one, else
   none (never the thread cache). */
static inline int shared_cache(void)
{
    return t_sh_cache1 ? JE_TCACHE(t_sh_cache1 - 1) : JE_TCACHE_NONE;
}

/* A slot's shared arena. */
static inline int shared_flags(int slot)
{
    return JE_ARENA(slots[slot].shared_arena) | shared_cache();
}

static inline bool je_fast(int slot)
{
    return je_real.malloc && (slot == 0 || t_bound);
}

static inline void *be_malloc(int slot, size_t n)
{
    if (!g_je)
        return __libc_malloc(n);
    return je_fast(slot) ? je_real.malloc(n) : mallocx(n ? n : 1, je_flags(slot));
}

/* shared: shared_block(p, ...), which the caller knows. */
static inline void be_free_as(void *p, bool shared)
{
    if (!g_je) {
        if (unlikely(shared))
            ON_SHARED_ARENA(__libc_free(p));
        else
            __libc_free(p);
    } else if (unlikely(shared))
        dallocx(p, shared_cache()); /* never into the thread cache */
    else if (je_real.free)
        je_real.free(p); /* into this thread's own cache */
    else
        dallocx(p, 0);
}

static inline void be_free(void *p)
{
    be_free_as(p, in_shared(p));
}

static inline size_t be_usable(void *p)
{
    if (g_je)
        return sallocx(p, 0);
    return glibc_usable_size ? glibc_usable_size(p) : 0;
}

static void *be_aligned(int slot, size_t align, size_t n)
{
    if (!g_je)
        return __libc_memalign(align, n);
    if (align < sizeof(void *))
        align = sizeof(void *);
    return mallocx(n ? n : 1, JE_LG_ALIGN(__builtin_ctzl(align)) | je_flags(slot));
}

/* ---------------------------------------------------------------------- */
/* Memory in use, per slot, and budgets (cga_slot_set_limit).              */
/*
 * A node process's memory in use: the sizes of the blocks its tasks got and
 * that have not been freed into its arena yet (a block another slot frees
 * counts until the owner drains it from its hand-over stack), plus its
 * Python small objects (pyalloc.c).  Its main task counts in t_bytes (only
 * it writes that word: no atomic add), its other threads in the slot's
 * live[s].bytes, as do glibc's mmapped blocks, which anyone may free: the
 * big-block table (bigblocks.c) says whose each is.  Sizes are the
 * allocator's: glibc's chunk size (the block and its header), jemalloc's
 * usable size.  Not counted: memory a node maps itself, its thread stacks,
 * what was allocated before the guard was active.  A new process in a slot
 * starts at 0; blocks of an earlier process it frees make it lower (the
 * total is read as at least 0).
 */

static inline size_t block_bytes(void *p)
{
    return g_je ? sallocx(p, 0) : ((size_t *)p)[-1] & ~(size_t)7;
}

static inline bool glibc_mmapped(void *p)
{
    return !g_je && (((size_t *)p)[-1] & GLIBC_IS_MMAPPED);
}

static inline void count(int s, long n)
{
    if (t_bound)
        atomic_store_explicit(&t_bytes, atomic_load_explicit(&t_bytes, memory_order_relaxed) + n,
                              memory_order_relaxed);
    else
        atomic_fetch_add_explicit(&live[s].bytes, n, memory_order_relaxed);
}

/* Block p, just got by slot s (0: the container, not counted). */
static inline void count_got(int s, void *p)
{
    if (!p || !s)
        return;
    if (unlikely(glibc_mmapped(p))) {
        if (bb_put(p, s))
            atomic_fetch_add_explicit(&live[s].bytes, (long)block_bytes(p), memory_order_relaxed);
        return;
    }
    count(s, (long)block_bytes(p));
}

/* Block p, about to be freed into its arena by slot s, its owner's (or
   unmapped by anyone: then the table says whose it was). */
static inline void count_freed(int s, void *p)
{
    if (unlikely(glibc_mmapped(p))) {
        int got = bb_take(p);
        if (got > 0)
            atomic_fetch_sub_explicit(&live[got].bytes, (long)block_bytes(p), memory_order_relaxed);
        return;
    }
    if (s)
        count(s, -(long)block_bytes(p));
}

static long slot_bytes(int s)
{
    _Atomic long *main = atomic_load_explicit(&live[s].main_bytes, memory_order_acquire);
    long n = atomic_load_explicit(&live[s].bytes, memory_order_relaxed) +
             (main ? atomic_load_explicit(main, memory_order_relaxed) : 0) + py_slot_bytes(s);
    return n > 0 ? n : 0;
}

static __attribute__((noreturn, cold, noinline)) void over_budget(int s, long used, size_t n)
{
    /* The figures first, for the CRASHED event (cga_slot_memory), then the
       end: SIGKILL to its own process, outside the allocator's bracket, so
       its arena stays in use for the next process in the slot. */
    atomic_store(&live[s].over_asked, (uint64_t)n ? (uint64_t)n : 1);
    atomic_store(&live[s].over_used, (uint64_t)used);
    syscall(SYS_kill, syscall(SYS_getpid), SIGKILL);
    for (;;)
        pause();
}

/* What a block asked as n bytes will count (block_bytes) once got: jemalloc's
   size class (an 8 MiB bytearray's 8 MiB + 57 B is a 10 MiB block), glibc's
   chunk (n and its header, 16-aligned; an mmapped chunk is page-rounded,
   less than 4 KiB more than this). */
static inline size_t bytes_for(size_t n)
{
    if (g_je)
        return nallocx(n ? n : 1, 0);
    size_t chunk = (n + sizeof(size_t) + 15) & ~(size_t)15;
    return chunk < 32 ? 32 : chunk;
}

/* Before slot s counts `more` bytes more: one load while it has no budget. */
static inline void within_budget(int s, size_t more)
{
    uint64_t limit = atomic_load_explicit(&slots[s].limit, memory_order_relaxed);
    if (likely(!limit) || !s)
        return;
    long used = slot_bytes(s);
    if ((uint64_t)used + more > limit)
        over_budget(s, used, more);
}

/* Before slot s turns a block of `have` bytes (0: none) into one asked as n
   bytes: judged on what the new block will count, so that no allocation
   lands over the budget (the size is worked out only under a budget). */
static inline void block_within_budget(int s, size_t n, size_t have)
{
    if (likely(!atomic_load_explicit(&slots[s].limit, memory_order_relaxed)) || !s)
        return;
    size_t will = bytes_for(n);
    within_budget(s, will > have ? will - have : 0);
}

HIDDEN void cga_within_budget(int s, size_t n)
{
    within_budget(s, n);
}

/* ---------------------------------------------------------------------- */
/* Which slot the calling task is, and what it must do on each call.      */

static int learn_glibc_arena(int slot)
{
    /* Whatever arena glibc attached to this thread (a new one, or one a
       thread that ended cleanly gave back) serves this slot from now on. */
    void *probe = __libc_malloc(GLIBC_PROBE_SIZE);
    if (!probe)
        return 0;
    void *arena = glibc_arena_of(probe);
    int o = arena ? glibc_arena_claim(arena, slot) : 0;
    t_arena = o ? arena : NULL;
    __libc_free(probe);
    return o;
}

/* A node process's block from glibc's main arena means it held the
   container's arena lock: count it (allocator.MMAP_THRESHOLD says why it
   should not happen). */
static inline void *check_main(int slot, void *p)
{
    if (!g_je && slot && p && !(((size_t *)p)[-1] & (GLIBC_IS_MMAPPED | GLIBC_NON_MAIN_ARENA)))
        atomic_fetch_add_explicit(&slots[slot].main_allocs, 1, memory_order_relaxed);
    return p;
}

/* The main task's word is read only after its death: program order is all
   that matters, and the compiler must keep it. */
static inline void enter(int slot)
{
    if (!slot)
        return;
    if (t_bound) {
        t_inside++;
        atomic_signal_fence(memory_order_seq_cst);
    } else {
        atomic_fetch_add_explicit(&live[slot].inside, 1, memory_order_seq_cst);
    }
}

static inline void leave(int slot)
{
    if (!slot)
        return;
    if (t_bound) {
        atomic_signal_fence(memory_order_seq_cst);
        t_inside--;
    } else {
        atomic_fetch_sub_explicit(&live[slot].inside, 1, memory_order_seq_cst);
    }
}

int cga_slot_of_pid(int pid)
{
    if (pid != g_container_pid)
        for (int i = 1; i < g_nslots; i++)
            if (atomic_load_explicit(&live[i].pid, memory_order_acquire) == pid)
                return i;
    return 0;
}

static __attribute__((noinline)) int resolve_slot(void)
{
    int s = cga_slot_of_pid((int)syscall(SYS_getpid));
    t_slot1 = s + 1;
    if (g_je) {
        t_owner = s;
    } else {
        enter(s);
        t_owner = learn_glibc_arena(s);
        leave(s);
    }
    return s;
}

static inline int my_slot(void)
{
    int s1 = t_slot1;
    return likely(s1) ? s1 - 1 : resolve_slot();
}

int cga_caller_slot(void)
{
    return likely(atomic_load_explicit(&g_active, memory_order_relaxed)) ? my_slot() : 0;
}

int cga_caller_bound(void)
{
    return t_bound;
}

/* A block on a hand-over stack carries, in its second word (blocks of 16 B
   and more), its own address mixed with this mark.  A second free of it
   before its owner freed it (a double free across nodes) finds the mark and
   kills the freer: otherwise the owner, not the faulty node, would pay (it
   would free the block twice, or follow a stack linked to itself in
   drain_stack forever, holding whatever it held: the GIL).  The owner frees
   the last HELD_BLOCKS blocks of up to HELD_MAX bytes handed over not when
   its drain takes them off the stack but at its next drain (owner.held):
   the two frees of a double free are often a few microseconds apart, and a
   drain may fall between them.  A second free after that, or of another
   block after the drain, is not caught. */
#define HANDED_MARK ((uintptr_t)0x68616e6465642121ull) /* "handed!!" */
#define HELD_MAX 1024  /* bytes: blocks held a drain long are this small */
#define HELD_BLOCKS 64 /* and this many at most, the last handed over */

static inline uintptr_t *mark_word(void *p)
{
    return be_usable(p) >= 2 * sizeof(void *) ? &((uintptr_t *)p)[1] : NULL;
}

static __attribute__((noreturn, cold, noinline)) void freed_twice(void *p, int o)
{
    char msg[160];
    int n = snprintf(msg, sizeof msg,
                     "cloneguard: double free: block %p of allocator slot %d was freed again "
                     "before its owner freed it; aborting the freer\n",
                     p, owner_slot(o));
    if (n > 0 && write(2, msg, (size_t)n) < 0)
        n = 0;
    abort();
}

static void free_handed(void *p)
{
    uintptr_t *mark = mark_word(p);
    if (mark)
        *mark = 0;
    be_free(p);
}

/* Take the blocks handed to o (counted freed by slot s): the small ones are
   held, marked, until the next drain frees them; the rest are freed now.
   Only exchanges touch o, so tasks of one slot may drain it at once. */
static void drain_stack(struct owner *o, int s)
{
    uint32_t pkru = hk_open(); /* the tables are the container's */
    void *p = atomic_exchange_explicit(&o->stack, NULL, memory_order_acquire);
    hk_close(pkru);
    void *keep = NULL, **tail = &keep; /* in stack order: the last handed first */
    int kept = 0;
    while (p) {
        void *next = *(void **)p;
        count_freed(s, p);
        if (kept < HELD_BLOCKS && be_usable(p) <= HELD_MAX) {
            *tail = p;
            tail = (void **)p;
            *tail = NULL;
            kept++;
        } else {
            free_handed(p);
        }
        p = next;
    }
    pkru = hk_open();
    void *old = atomic_exchange_explicit(&o->held, keep, memory_order_acq_rel);
    hk_close(pkru);
    while (old) {
        void *next = *(void **)old;
        free_handed(old);
        old = next;
    }
}

/* Free what others handed to this task's owner(s).  Called inside. */
static inline void drain_mine(int slot)
{
    struct owner *mine = &owners[t_owner];
    if (unlikely(atomic_load_explicit(&mine->stack, memory_order_relaxed)))
        drain_stack(mine, slot);
    if (t_sh_owner &&
        unlikely(atomic_load_explicit(&owners[t_sh_owner].stack, memory_order_relaxed)))
        drain_stack(&owners[t_sh_owner], slot);
    if (slot == 0 && t_owner != 0 &&
        unlikely(atomic_load_explicit(&owners[0].stack, memory_order_relaxed)))
        drain_stack(&owners[0], 0);
}

static void hand_over(int o, void *p)
{
    if (owner_slot(o) == 0)
        o = 0; /* any container thread frees it */
    struct owner *to = &owners[o];
    void *head = atomic_load_explicit(&to->stack, memory_order_relaxed);
    uintptr_t *mark = mark_word(p);
    if (mark && *mark == (HANDED_MARK ^ (uintptr_t)p))
        freed_twice(p, o);
    uint32_t pkru = hk_open(); /* p is under the owner's key, the
                                  stack under the container's */
    if (mark)
        *mark = HANDED_MARK ^ (uintptr_t)p;
    do
        *(void **)p = head;
    while (!atomic_compare_exchange_weak_explicit(&to->stack, &head, p, memory_order_release,
                                                  memory_order_relaxed));
    atomic_fetch_add_explicit(&to->handed, 1, memory_order_relaxed);
    hk_close(pkru);
}

/* ---------------------------------------------------------------------- */
/* Shared blocks (the split): the ROS stack's and the interpreter's, from the
   calling slot's shared arena; plain malloc for the container and for tasks
   without one (a node process's other threads under glibc).  With keys,
   memory every node may write (heapkeys.c).                               */

static inline bool shared_slot(int *s)
{
    if (!atomic_load_explicit(&g_active, memory_order_relaxed))
        return false;
    *s = my_slot();
    return *s != 0 && has_shared();
}

static inline void *be_shared(int s, size_t n, size_t align, bool zero)
{
    if (!g_je) {
        void *p;
        ON_SHARED_ARENA(p = align > 16 ? __libc_memalign(align, n)
                            : zero     ? __libc_calloc(1, n)
                                       : __libc_malloc(n));
        return p;
    }
    return mallocx(n ? n : 1, shared_flags(s) | (zero ? JE_ZERO : 0) |
                                  (align > 16 ? JE_LG_ALIGN(__builtin_ctzl(align)) : 0));
}

static inline void *be_shared_realloc(int s, void *p, size_t n)
{
    if (g_je)
        return rallocx(p, n ? n : 1, shared_flags(s));
    void *q;
    ON_SHARED_ARENA(q = __libc_realloc(p, n));
    return q;
}

static void *shared_in(int s, size_t n, size_t align, bool zero)
{
    block_within_budget(s, n, 0);
    enter(s);
    drain_mine(s);
    /* Most of a Python node's allocating comes this way. */
    cga_stop_point(s, CGA_STOP_ALLOCATION);
    void *p = be_shared(s, n, align, zero);
    leave(s);
    count_got(s, p);
    return p;
}

/* The caller of the operator new being served (set by our new, read by the
   malloc libstdc++'s new calls), so that a block is attributed to the code
   that asked for it, not to libstdc++. */
static __thread const void *t_new_caller __attribute__((tls_model("initial-exec")));

/* Does this call, from ra, want a shared block?  Yes when it comes from
   the ROS stack or the interpreter (heapkeys.c says which, and why): their
   structures are walked, and with keys written, by every node process. */
static inline bool wants_shared(int s, const void *ra)
{
    if (!s)
        return false;
    const void *pc = t_new_caller;
    t_new_caller = NULL;
    return has_shared() && hk_shared_caller(pc ? pc : ra);
}

HIDDEN void *cga_shared_alloc(size_t n, bool zero)
{
    int s;
    if (!shared_slot(&s))
        return zero ? calloc(1, n) : malloc(n);
    return shared_in(s, n, 0, zero);
}

HIDDEN void *cga_shared_realloc(void *p, size_t n)
{
    int s;
    if (!p)
        return cga_shared_alloc(n, false);
    if (!shared_slot(&s))
        return realloc(p, n);
    int o = owner_of(p);
    if (shared_block(p, o) && owner_slot(o) == s) {
        block_within_budget(s, n, block_bytes(p));
        enter(s);
        drain_mine(s);
        count_freed(s, p);
        void *q = be_shared_realloc(s, p, n);
        leave(s);
        count_got(s, q ? q : p);
        return q;
    }
    /* Another slot's block, or one from before (the container's): moved
       into ours, so that it stays writable by all. */
    size_t have = be_usable(p);
    void *q = cga_shared_alloc(n, false);
    if (q) {
        memcpy(q, p, have < n ? have : n);
        free(p);
    }
    return q;
}

/* ---------------------------------------------------------------------- */
/* The interposed C API.                                                   */

static void *malloc_from(size_t n, const void *ra)
{
    if (unlikely(!atomic_load_explicit(&g_active, memory_order_relaxed)))
        return be_malloc(0, n);
    int s = my_slot();
    if (unlikely(wants_shared(s, ra))) {
        void *p = shared_in(s, n, 0, false);
        if (!p)
            errno = ENOMEM;
        return p;
    }
    block_within_budget(s, n, 0);
    enter(s);
    drain_mine(s);
    cga_stop_point(s, CGA_STOP_ALLOCATION);
    void *p = check_main(s, be_malloc(s, n));
    leave(s);
    count_got(s, p);
    if (!p)
        errno = ENOMEM;
    return p;
}

EXPORT void *malloc(size_t n)
{
    return malloc_from(n, __builtin_return_address(0));
}

EXPORT void free(void *p)
{
    if (!p)
        return;
    if (unlikely(!atomic_load_explicit(&g_active, memory_order_relaxed))) {
        be_free(p);
        return;
    }
    int s = my_slot();
    int o = owner_of(p);
    if (o < 0 || owner_slot(o) == s) {
        enter(s);
        drain_mine(s);
        count_freed(s, p);
        be_free_as(p, shared_block(p, o));
        leave(s);
    } else {
        hand_over(o, p);
    }
}

EXPORT void *calloc(size_t n, size_t size)
{
    size_t total;
    if (__builtin_mul_overflow(n, size, &total)) {
        errno = ENOMEM;
        return NULL;
    }
    int s = atomic_load_explicit(&g_active, memory_order_relaxed) ? my_slot() : 0;
    if (unlikely(wants_shared(s, __builtin_return_address(0)))) {
        void *p = shared_in(s, total, 0, true);
        if (!p)
            errno = ENOMEM;
        return p;
    }
    block_within_budget(s, total, 0);
    enter(s);
    if (s)
        drain_mine(s);
    cga_stop_point(s, CGA_STOP_ALLOCATION);
    void *p = check_main(s, !g_je        ? __libc_calloc(n, size)
                            : je_fast(s) ? je_real.calloc(n, size)
                                         : mallocx(total ? total : 1, JE_ZERO | je_flags(s)));
    leave(s);
    count_got(s, p);
    if (!p)
        errno = ENOMEM;
    return p;
}

EXPORT void *realloc(void *p, size_t n)
{
    if (!p)
        return malloc_from(n, __builtin_return_address(0));
    if (n == 0) { /* glibc's semantics: free, return NULL */
        free(p);
        return NULL;
    }
    int active = atomic_load_explicit(&g_active, memory_order_relaxed);
    int s = active ? my_slot() : 0;
    int o = active ? owner_of(p) : 0;
    void *q;
    if (o < 0 || owner_slot(o) == s) {
        if (active)
            block_within_budget(s, n, block_bytes(p));
        enter(s);
        drain_mine(s);
        if (active)
            count_freed(s, p);
        q = check_main(s, shared_block(p, o) ? be_shared_realloc(s, p, n)
                          : !g_je            ? __libc_realloc(p, n)
                          : je_fast(s)       ? je_real.realloc(p, n)
                                             : rallocx(p, n, je_flags(s)));
        leave(s);
        if (active)
            count_got(s, q ? q : p); /* a failed realloc leaves p as it was */
    } else {
        /* Someone else's block: copy it into ours (shared if it was), hand
           theirs back. */
        size_t have = be_usable(p);
        q = shared_block(p, o) ? shared_in(s, n, 0, false)
                               : malloc_from(n, __builtin_return_address(0));
        if (q) {
            memcpy(q, p, have < n ? have : n);
            hand_over(o, p);
        }
    }
    if (!q)
        errno = ENOMEM;
    return q;
}

EXPORT void *reallocarray(void *p, size_t n, size_t size)
{
    size_t total;
    if (__builtin_mul_overflow(n, size, &total)) {
        errno = ENOMEM;
        return NULL;
    }
    return realloc(p, total);
}

static void *aligned(size_t align, size_t n, const void *ra)
{
    if (align & (align - 1)) /* glibc rounds up to a power of two */
        align = (size_t)1 << (64 - __builtin_clzl(align));
    int s = atomic_load_explicit(&g_active, memory_order_relaxed) ? my_slot() : 0;
    if (unlikely(wants_shared(s, ra))) {
        void *p = shared_in(s, n, align, false);
        if (!p)
            errno = ENOMEM;
        return p;
    }
    block_within_budget(s, n, 0);
    enter(s);
    if (s)
        drain_mine(s);
    cga_stop_point(s, CGA_STOP_ALLOCATION);
    void *p = check_main(s, be_aligned(s, align, n));
    leave(s);
    count_got(s, p);
    if (!p)
        errno = ENOMEM;
    return p;
}

#define RA __builtin_return_address(0)
EXPORT void *memalign(size_t align, size_t n)
{
    return aligned(align, n, RA);
}
EXPORT void *aligned_alloc(size_t align, size_t n)
{
    return aligned(align, n, RA);
}
EXPORT void *valloc(size_t n)
{
    return aligned(g_page, n, RA);
}

EXPORT void *pvalloc(size_t n)
{
    size_t rounded = (n + g_page - 1) & ~(g_page - 1);
    return aligned(g_page, rounded ? rounded : g_page, RA);
}

EXPORT int posix_memalign(void **out, size_t align, size_t n)
{
    if (align < sizeof(void *) || (align & (align - 1)))
        return EINVAL;
    int saved = errno;
    void *p = aligned(align, n, RA);
    errno = saved;
    if (!p)
        return ENOMEM;
    *out = p;
    return 0;
}

EXPORT size_t malloc_usable_size(void *p)
{
    if (!p)
        return 0;
    if (!g_je && !glibc_usable_size)
        glibc_usable_size = (size_t(*)(void *))dlsym(RTLD_NEXT, "malloc_usable_size");
    return be_usable(p);
}

/* ---------------------------------------------------------------------- */
/* C++ operator new / delete.  jemalloc defines them too, and would
   otherwise serve C++ code without us: new forwards to libstdc++'s own (which
   calls our malloc and keeps its new_handler and bad_alloc semantics),
   delete is free.                                                         */

#define NEW_OPS(X)                                                                                 \
    X(_Znwm, (size_t n), (n), n, 0, 0)                                                             \
    X(_Znam, (size_t n), (n), n, 0, 0)                                                             \
    X(_ZnwmRKSt9nothrow_t, (size_t n, const void *t), (n, t), n, 0, 1)                             \
    X(_ZnamRKSt9nothrow_t, (size_t n, const void *t), (n, t), n, 0, 1)                             \
    X(_ZnwmSt11align_val_t, (size_t n, size_t a), (n, a), n, a, 0)                                 \
    X(_ZnamSt11align_val_t, (size_t n, size_t a), (n, a), n, a, 0)                                 \
    X(_ZnwmSt11align_val_tRKSt9nothrow_t, (size_t n, size_t a, const void *t), (n, a, t), n, a, 1) \
    X(_ZnamSt11align_val_tRKSt9nothrow_t, (size_t n, size_t a, const void *t), (n, a, t), n, a, 1)

static void *libstdcxx(const char *name)
{
    void *h = dlopen("libstdc++.so.6", RTLD_LAZY | RTLD_NOLOAD);
    void *f = h ? dlsym(h, name) : NULL;
    if (h)
        dlclose(h);
    return f;
}

/* Without libstdc++'s (a process that never loaded it): no new_handler. */
static void *new_fallback(size_t n, size_t align, int nothrow)
{
    void *p = align ? aligned(align, n, RA) : malloc_from(n ? n : 1, RA);
    if (!p && !nothrow)
        abort();
    return p;
}

#define DECLARE_NEW(name, params, args, n_, align_, nothrow_) EXPORT void *name params;
NEW_OPS(DECLARE_NEW)

#define DEFINE_NEW(name, params, args, n_, align_, nothrow_)                                       \
    static void *(*_Atomic real_##name)params;                                                     \
    EXPORT void *name params                                                                       \
    {                                                                                              \
        void *(*f)params = real_##name;                                                            \
        if (unlikely(!f))                                                                          \
            f = real_##name = (void *(*)params)libstdcxx(#name);                                   \
        t_new_caller = RA; /* for wants_shared; cleared below */                                   \
        void *p = f ? f args : new_fallback(n_, align_, nothrow_);                                 \
        t_new_caller = NULL;                                                                       \
        return p;                                                                                  \
    }
NEW_OPS(DEFINE_NEW)

static void resolve_new_ops(void)
{
#define RESOLVE_NEW(name, params, args, n_, align_, nothrow_)                                      \
    if (!real_##name)                                                                              \
        real_##name = (void *(*)params)libstdcxx(#name);
    NEW_OPS(RESOLVE_NEW)
}

/* The sizes, alignments and nothrow tags delete takes are not needed to
   free: unnamed parameters. */
#define DELETE_OPS(X)                                                                              \
    X(_ZdlPv, (void *p))                                                                           \
    X(_ZdaPv, (void *p))                                                                           \
    X(_ZdlPvm, (void *p, size_t))                                                                  \
    X(_ZdaPvm, (void *p, size_t))                                                                  \
    X(_ZdlPvRKSt9nothrow_t, (void *p, const void *))                                               \
    X(_ZdaPvRKSt9nothrow_t, (void *p, const void *))                                               \
    X(_ZdlPvSt11align_val_t, (void *p, size_t))                                                    \
    X(_ZdaPvSt11align_val_t, (void *p, size_t))                                                    \
    X(_ZdlPvmSt11align_val_t, (void *p, size_t, size_t))                                           \
    X(_ZdaPvmSt11align_val_t, (void *p, size_t, size_t))                                           \
    X(_ZdlPvSt11align_val_tRKSt9nothrow_t, (void *p, size_t, const void *))                        \
    X(_ZdaPvSt11align_val_tRKSt9nothrow_t, (void *p, size_t, const void *))

#define DECLARE_DELETE(name, params) EXPORT void name params;
DELETE_OPS(DECLARE_DELETE)

#define DEFINE_DELETE(name, params)                                                                \
    EXPORT void name params                                                                        \
    {                                                                                              \
        free(p);                                                                                   \
    }
DELETE_OPS(DEFINE_DELETE)

/* ---------------------------------------------------------------------- */
/* jemalloc extent hooks: a slot's arena gets its memory from the slot's
   own address range, bumped forward, never given back (jemalloc retains
   and purges instead).  The bump is one CAS: a task killed in here leaves
   at worst a little address space unused.                                */

static void *hook_alloc(je_hooks *h, void *new_addr, size_t size, size_t align, bool *zero,
                        bool *commit, unsigned arena_ind)
{
    (void)arena_ind;
    struct slot_hooks *sl = (struct slot_hooks *)h;
    if (align < g_page)
        align = g_page;
    uintptr_t cur = atomic_load(sl->bump), start;
    do {
        start = new_addr ? (uintptr_t)new_addr : (cur + align - 1) & ~(align - 1);
        if ((new_addr && start != cur) || start + size > sl->limit || start + size < start)
            return NULL;
    } while (!atomic_compare_exchange_weak(sl->bump, &cur, start + size));
    if (mprotect((void *)start, size, PROT_READ | PROT_WRITE) != 0)
        return NULL;
    *zero = true; /* never handed out before: zero pages */
    *commit = true;
    return (void *)start;
}

static bool hook_dalloc(je_hooks *h, void *a, size_t n, bool c, unsigned i)
{
    (void)h, (void)a, (void)n, (void)c, (void)i;
    return true; /* opt out: jemalloc keeps it */
}

static void hook_destroy(je_hooks *h, void *a, size_t n, bool c, unsigned i)
{
    (void)h, (void)c, (void)i;
    madvise(a, n, MADV_DONTNEED);
}

static bool hook_commit(je_hooks *h, void *a, size_t n, size_t off, size_t len, unsigned i)
{
    (void)h, (void)n, (void)i;
    return mprotect((char *)a + off, len, PROT_READ | PROT_WRITE) != 0;
}

static bool hook_decommit(je_hooks *h, void *a, size_t n, size_t off, size_t len, unsigned i)
{
    (void)h, (void)a, (void)n, (void)off, (void)len, (void)i;
    return true; /* opt out: purged instead */
}

static bool hook_purge_lazy(je_hooks *h, void *a, size_t n, size_t off, size_t len, unsigned i)
{
    (void)h, (void)n, (void)i;
    return madvise((char *)a + off, len, MADV_FREE) != 0;
}

static bool hook_purge_forced(je_hooks *h, void *a, size_t n, size_t off, size_t len, unsigned i)
{
    (void)h, (void)n, (void)i;
    return madvise((char *)a + off, len, MADV_DONTNEED) != 0;
}

static bool hook_split(je_hooks *h, void *a, size_t n, size_t x, size_t y, bool c, unsigned i)
{
    (void)h, (void)a, (void)n, (void)x, (void)y, (void)c, (void)i;
    return false; /* within one slot's range: fine */
}

static bool hook_merge(je_hooks *h, void *a, size_t n, void *b, size_t m, bool c, unsigned i)
{
    (void)h, (void)a, (void)n, (void)b, (void)m, (void)c, (void)i;
    return false; /* jemalloc merges only within an arena */
}

/* ---------------------------------------------------------------------- */
/* jemalloc's address map, made in advance.
 *
 * jemalloc maps every page it hands out to its extent in one process-wide
 * radix tree whose leaves (2 MiB each) cover 1 GiB of address space each
 * and are made on first use: under the tree's global init lock, from the
 * first base allocator's memory, under *its* global lock (b0).  A node
 * process whose arena first reaches a new GiB of its slot's range makes
 * that leaf itself; SIGKILLed there, it leaves both global locks held and
 * the container's next arenas.create (which takes b0's lock) hangs (seen
 * once in 300 malloc kills).  So the container makes every leaf of a new
 * arena's range: it allocates the biggest block the range holds (half of
 * it: jemalloc never merges what two hook calls gave, so this is the
 * largest block a node can get, 4 GiB; with extents capped at 1 GiB, as
 * before, a malloc over 896 MiB failed), then the whole range in pieces of
 * 512 MiB and less (each piece's first and last pages are entered in the
 * tree, so every GiB gets its leaf), and frees and purges it all.  The
 * arena keeps the range as retained extents and reuses it; the hooks are
 * not asked for memory again.  About 0.9 ms a slot (both arenas; 1.4-2.0
 * ms with the 1 GiB cap, interleaved runs of 40 slots); nothing is written
 * to the pages.
 *
 * Skipped under strict overcommit (vm.overcommit_memory=2): making the
 * range writable would charge all 16 GiB against the commit limit.  Then
 * the window stays, once per GiB a node process reaches.                  */

static int strict_overcommit(void)
{
    char c = '0';
    int fd = open("/proc/sys/vm/overcommit_memory", O_RDONLY | O_CLOEXEC);
    if (fd >= 0) {
        if (read(fd, &c, 1) != 1)
            c = '0';
        close(fd);
    }
    return c == '2';
}

static void make_address_map(unsigned arena, size_t span)
{
    if (strict_overcommit())
        return;
    char name[64];
    size_t limit = span;
    snprintf(name, sizeof name, "arena.%u.retain_grow_limit", arena);
    if (mallctl(name, NULL, NULL, &limit, sizeof limit) != 0)
        return;
    static const size_t pieces[] = {(size_t)512 << 20, (size_t)64 << 20, (size_t)8 << 20};
    void *held[(1 << (SLOT_SHIFT - 23)) + 64];
    size_t n = 0;
    int flags = JE_ARENA(arena) | JE_TCACHE_NONE;
    /* First the biggest block the range holds, given back at once: what
       jemalloc gets from one hook call it never merges with the next (it
       cannot know the hooks would agree), so the largest block a node can
       have is the largest extent made here. */
    for (size_t big = span / 2; big >= pieces[0]; big /= 2) {
        void *p = mallocx(big, flags);
        if (p) {
            dallocx(p, JE_TCACHE_NONE);
            break;
        }
    }
    for (size_t i = 0; i < sizeof pieces / sizeof pieces[0]; i++) {
        void *p;
        while (n < sizeof held / sizeof held[0] && (p = mallocx(pieces[i], flags)) != NULL)
            held[n++] = p;
    }
    while (n > 0)
        dallocx(held[--n], JE_TCACHE_NONE);
    snprintf(name, sizeof name, "arena.%u.purge", arena);
    mallctl(name, NULL, NULL, NULL, 0);
}

/* ---------------------------------------------------------------------- */
/* --core-dumps (core_dumps.py): what to leave out of a dump.
 *
 * gdb writes every mapping it can read, and reads even the PROT_NONE
 * reservation jemalloc's slots carve from (16 GiB a slot, for every slot
 * the container could have: TiBs), and under jemalloc every made slot's
 * range is readable once its address map is made: a dump would write TiBs
 * of zeros.  So while one is written the whole reservation is
 * MADV_DONTDUMP but for the resident runs of each made slot's range (what a
 * node process really uses; a page never touched, or purged, is zeros as
 * far as a dump is concerned), gaps under DUMP_MIN_RUN kept in (their zeros
 * become holes afterwards: dumps.c digs them), which bounds how many
 * mappings the marking splits.  A page first touched while the dump is
 * written is left out of that one dump; on a machine with swap, so is a
 * page swapped out (it reads as not resident).  Afterwards the reservation
 * is put back as it was (MADV_DODUMP; the mappings merge again).  Also
 * Python's pools' never-used tail (pyalloc.c).  On the monitor thread, one
 * dump at a time.  Its cost is mincore over every made slot's 16 GiB, ~10
 * ms a slot in the kernel (0.47-0.48 s at 48 slots, 0.77-0.89 s at 96;
 * cga_dump_exclude timed in a process with the guard and jemalloc
 * preloaded), during which the monitor reports no other death.            */

#define DUMP_MIN_RUN ((uintptr_t)2 << 20)

static int dump_keep(uintptr_t from, uintptr_t to)
{
    return madvise((void *)from, to - from, MADV_DODUMP) ? -errno : 0;
}

/* Put the resident runs of [lo, hi) back into dumps. */
static int dump_keep_resident(uintptr_t lo, uintptr_t hi)
{
    static unsigned char vec[1 << 16]; /* 256 MiB of pages a call */
    uintptr_t from = 0, to = 0;        /* the run being gathered, or 0 */
    for (uintptr_t at = lo; at < hi;) {
        size_t pages = (hi - at) / g_page;
        if (pages > sizeof vec)
            pages = sizeof vec;
        if (mincore((void *)at, pages * g_page, vec) != 0)
            return -errno;
        for (size_t i = 0; i < pages; i++, at += g_page) {
            if (!(vec[i] & 1))
                continue;
            if (from && at - to >= DUMP_MIN_RUN) {
                int r = dump_keep(from, to);
                if (r)
                    return r;
                from = 0;
            }
            if (!from)
                from = at;
            to = at + g_page;
        }
    }
    return from ? dump_keep(from, to) : 0;
}

EXPORT int cga_dump_exclude(int exclude)
{
    int r = py_dump_tail(exclude);
    if (r || !g_je || !g_region_len)
        return r;
    if (madvise((void *)g_region, g_region_len, exclude ? MADV_DONTDUMP : MADV_DODUMP) != 0)
        return -errno;
    for (int s = 1; exclude && s < NSLOTS && !r; s++) {
        const struct slot *sl = &slots[s];
        if (sl->hooks.limit) /* made: its range is readable */
            r = dump_keep_resident(sl->hooks.base, sl->shared_hooks.limit);
    }
    return r;
}

/* ---------------------------------------------------------------------- */
/* Control, for the clone core.                                            */

static void after_fork_child(void)
{
    /* A fork()ed copy is an ordinary process: nobody shares its memory. */
    atomic_store(&g_active, 0);
}

EXPORT const char *cga_backend(void)
{
    return mallocx ? "jemalloc" : "glibc";
}

/* glibc: find thread_arena and tcache (GLIBC_TCACHE_CHUNK says what they
   are) in libc's TLS block, on a new thread that has just allocated: the one
   word there that is its arena, and the one that points at a cache-sized
   chunk of that arena.  Sets g_tls_arena and g_tls_tcache, or leaves them
   0. */
struct libc_tls {
    char *block;
    size_t len;
};

static int find_libc_tls(struct dl_phdr_info *info, size_t size, void *arg)
{
    (void)size;
    struct libc_tls *t = arg;
    if (!info->dlpi_name || !strstr(info->dlpi_name, "/libc.so"))
        return 0;
    for (int i = 0; i < info->dlpi_phnum; i++)
        if (info->dlpi_phdr[i].p_type == PT_TLS) {
            t->block = info->dlpi_tls_data;
            t->len = info->dlpi_phdr[i].p_memsz;
        }
    return 1;
}

/* Can p be read?  (msync fails with ENOMEM on a page not mapped.) */
static bool mapped(const void *p)
{
    uintptr_t page = (uintptr_t)p & ~(uintptr_t)(g_page - 1);
    return page && msync((void *)page, g_page, MS_ASYNC) == 0;
}

static void *tls_probe_thread(void *unused)
{
    (void)unused;
    void *p = __libc_malloc(GLIBC_PROBE_SIZE);
    void *arena = p ? glibc_arena_of(p) : NULL;
    struct libc_tls t = {NULL, 0};
    dl_iterate_phdr(find_libc_tls, &t);
    long at_arena = -1, at_tcache = -1;
    int arenas = 0, tcaches = 0;
    for (size_t off = 0; arena && t.block && off + sizeof(void *) <= t.len; off += sizeof(void *)) {
        void *w = *(void **)(t.block + off);
        if (w == arena) {
            at_arena = (long)off;
            arenas++;
        } else if (w && ((uintptr_t)w & 15) == 0 && mapped((char *)w - sizeof(size_t)) &&
                   mapped((void *)((uintptr_t)w & ~(GLIBC_HEAP_MAX - 1))) &&
                   glibc_arena_of(w) == arena && block_bytes(w) == GLIBC_TCACHE_CHUNK) {
            at_tcache = (long)off;
            tcaches++;
        }
    }
    if (arenas == 1 && tcaches == 1) {
        uintptr_t tp;
        __asm__("mov %%fs:0, %0" : "=r"(tp));
        g_tls_arena = (long)((uintptr_t)t.block - tp) + at_arena;
        g_tls_tcache = (long)((uintptr_t)t.block - tp) + at_tcache;
    }
    __libc_free(p);
    return NULL;
}

static void find_glibc_tls(void)
{
    pthread_t t;
    if (pthread_create(&t, NULL, tls_probe_thread, NULL) == 0)
        pthread_join(t, NULL);
}

/* Start guarding.  Called once, by the container, before any node process
   exists.  0, or -errno (-ENOTSUP: glibc's per-thread malloc state is not
   where find_glibc_tls looks). */
EXPORT int cga_activate(int container_pid)
{
    if (atomic_load(&g_active))
        return -EALREADY;
    if (g_je && !(rallocx && dallocx && sallocx && nallocx && mallctl))
        return -ENOSYS;
    g_page = (size_t)sysconf(_SC_PAGESIZE);
    glibc_usable_size = (size_t(*)(void *))dlsym(RTLD_NEXT, "malloc_usable_size");
    if (!g_je && !glibc_usable_size)
        return -ENOSYS;
    if (g_je) {
        /* Address space for every slot, reserved (no memory, no commit
           charge); halved until the kernel agrees. */
        for (int n = NSLOTS; n >= 16; n /= 2) {
            size_t len = (size_t)(n - 1) << SLOT_SHIFT;
            void *r =
                mmap(NULL, len, PROT_NONE, MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE, -1, 0);
            if (r != MAP_FAILED) {
                g_region = (uintptr_t)r;
                g_region_len = len;
                g_nslots = n;
                break;
            }
        }
        if (!g_region)
            return -ENOMEM;
    }
    resolve_new_ops();
    if (g_je) {
#define REAL(name) je_real.name = (__typeof__(je_real.name))dlsym(RTLD_NEXT, #name)
        REAL(malloc);
        REAL(free);
        REAL(calloc);
        REAL(realloc);
#undef REAL
        if (!je_real.malloc || !je_real.free || !je_real.calloc || !je_real.realloc)
            memset(&je_real, 0, sizeof je_real); /* the *x API serves */
    }
    uintptr_t tp;
    __asm__("mov %%fs:0, %0" : "=r"(tp));
    g_inside_off = (long)((uintptr_t)&t_inside - tp);
    g_container_pid = container_pid;
    if (!g_je) {
        find_glibc_tls();
        if (!g_tls_arena || !g_tls_tcache)
            return -ENOTSUP;
    }
    g_keys = g_je && hk_enabled();
    if (g_keys) {
        int r = hk_tag_tables(&g_tables, sizeof g_tables);
        if (r)
            return r;
    }
    atomic_store(&slots[0].state, CGA_BOUND);
    atomic_store(&live[0].pid, container_pid);
    pthread_atfork(NULL, NULL, after_fork_child);
    atomic_store(&g_active, 1);
    return 0;
}

/* An arena carving from [base, base + len), its address map made.  0, or
   -errno. */
static int arena_new(struct slot_hooks *sh, _Atomic uintptr_t *bump, uintptr_t base, size_t len,
                     unsigned *out)
{
    sh->base = base;
    sh->limit = base + len;
    sh->bump = bump;
    atomic_store(bump, base);
    sh->h = (je_hooks){hook_alloc,      hook_dalloc,       hook_destroy, hook_commit, hook_decommit,
                       hook_purge_lazy, hook_purge_forced, hook_split,   hook_merge};
    je_hooks *hp = &sh->h;
    size_t sz = sizeof *out;
    int r = mallctl("arenas.create", out, &sz, &hp, sizeof hp);
    if (r)
        return -r;
    make_address_map(*out, len);
    return 0;
}

/* With protection keys, the unused slot a new context should take: slot s's
   key is fixed (hk_key_of_slot: node key (s-1) % nkeys), so it is the
   unused slot whose key the fewest live slots hold (pooled or running a
   node process; quarantined ones never run again), the lowest among equals.
   That way up to nkeys node processes each write under a key no other live
   one has, whatever slots were used and quarantined before, until every
   slot of every free key is used up.  Without keys (every slot's key 0),
   the first unused one.  0: none left. */
static int pick_unused_slot(void)
{
    int held[16] = {0}, best = 0; /* live slots by key (0: none) */
    for (int s = 1; s < g_nslots; s++) {
        int st = atomic_load_explicit(&slots[s].state, memory_order_relaxed);
        if (st == CGA_IDLE || st == CGA_BOUND)
            held[hk_key_of_slot(s)]++;
    }
    for (int s = 1; s < g_nslots; s++) {
        if (atomic_load_explicit(&slots[s].state, memory_order_relaxed) != CGA_UNUSED)
            continue;
        if (!best || held[hk_key_of_slot(s)] < held[hk_key_of_slot(best)])
            best = s;
        if (held[hk_key_of_slot(best)] == 0)
            break; /* nothing is less held */
    }
    return best;
}

/* A slot for a new node process context: its arena made (jemalloc) by the
   calling container thread.  The slot number, or -errno. */
EXPORT int cga_slot_new(void)
{
    if (!atomic_load(&g_active))
        return -ESRCH;
    for (int s; (s = pick_unused_slot()) > 0;) {
        int unused = CGA_UNUSED;
        if (!atomic_compare_exchange_strong(&slots[s].state, &unused, CGA_IDLE))
            continue; /* another thread took it: pick again */
        struct slot *sl = &slots[s];
        if (g_je) {
            uintptr_t base = g_region + ((uintptr_t)(s - 1) << SLOT_SHIFT);
            uintptr_t half = (uintptr_t)1 << HALF_SHIFT;
            int r = g_keys ? hk_tag(base, half, s) : 0;
            if (!r)
                r = arena_new(&sl->hooks, &live[s].bump, base, half, &sl->arena);
            if (!r)
                r = arena_new(&sl->shared_hooks, &live[s].shared_bump, base + half, half,
                              &sl->shared_arena);
            if (r) { /* its range stays reserved, unused */
                atomic_store(&sl->state, CGA_UNUSED);
                return r;
            }
            atomic_store(&owners[s].slot, s);
        }
        return s;
    }
    return -ENOSPC;
}

/* glibc: give the task whose TLS is current (a new context's, its own
   arena just attached) a second arena and cache, its shared arena: with
   both words of glibc's state cleared, glibc attaches another arena (a new
   one, or one a thread that ended gave back) and makes that arena's cache,
   exactly as for a new thread.  Then its own are put back.  0, or -errno
   (-ENOTSUP: the words are not what find_glibc_tls took them for). */
static int glibc_warm_shared(int slot)
{
    if (*tls_word(g_tls_arena) != t_arena || !*tls_word(g_tls_tcache))
        return -ENOTSUP;
    struct glibc_state own = glibc_swap((struct glibc_state){NULL, NULL});
    void *probe = __libc_malloc(GLIBC_PROBE_SIZE);
    struct glibc_state shared = glibc_swap(own);
    void *arena = probe ? glibc_arena_of(probe) : NULL;
    if (!arena || arena != shared.arena || arena == own.arena || !shared.tcache ||
        shared.tcache == own.tcache)
        return probe ? -ENOTSUP : -ENOMEM; /* the probe leaks */
    t_sh_arena = shared.arena;
    t_sh_tcache = shared.tcache;
    be_free(probe); /* into the shared arena: in_shared */
    t_sh_owner = glibc_arena_claim(arena, slot);
    if (!t_sh_owner)
        t_sh_arena = NULL;
    return t_sh_owner ? 0 : -ENOMEM;
}

/* Called with a new context's thread pointer current (contexts.c borrows
   its TLS block on a container thread): make this "task" slot s's and set
   up its allocator state (jemalloc's thread data and cache, glibc's arena
   and cache) now, in the container, so the node process never runs that
   set-up, which takes allocator-wide locks. */
EXPORT int cga_warm(int slot)
{
    if (slot <= 0 || slot >= g_nslots)
        return -EINVAL;
    t_slot1 = slot + 1;
    t_bound = 0;
    if (g_je) {
        t_owner = slot;
        void *p = mallocx(1, je_flags(slot)); /* thread data, cache */
        if (!p)
            return -ENOMEM;
        dallocx(p, 0);
        unsigned arena = slots[slot].arena; /* its thread arena */
        if (mallctl("thread.arena", NULL, NULL, &arena, sizeof arena) != 0)
            return -EINVAL;
        unsigned cache;
        size_t len = sizeof cache;
        if (mallctl("tcache.create", &cache, &len, NULL, 0) != 0)
            return -ENOMEM;
        t_sh_cache1 = cache + 1;
    } else {
        t_owner = learn_glibc_arena(slot);
        if (!t_owner)
            return -ENOMEM;
        int r = glibc_warm_shared(slot);
        if (r)
            return r;
    }
    t_inside = 0;
    t_bound = 1;
    return 0;
}

/* A context is about to run a new node process. */
EXPORT void cga_slot_bind(int slot)
{
    hk_refresh_shared();
    atomic_store(&live[slot].inside, 0);
    atomic_store(&slots[slot].state, CGA_BOUND);
}

/* First thing in a node process: threads it creates find their slot by pid. */
EXPORT void cga_child_start(void)
{
    int s = t_slot1 - 1;
    if (s > 0) {
        if (g_keys)
            hk_child_enter(s);
        stops_clear(s);            /* no request of an earlier process */
        atomic_store(&t_bytes, 0); /* its memory in use, from nothing */
        py_slot_begin(s);
        atomic_store(&live[s].bytes, 0);
        atomic_store(&live[s].over_used, 0);
        atomic_store(&live[s].over_asked, 0);
        atomic_store(&live[s].main_bytes, &t_bytes);
        atomic_store(&live[s].pid, (int)syscall(SYS_getpid));
    }
}

/* Where the guard's tables are (under the container's key with keys). */
EXPORT const void *cga_tables(size_t *len)
{
    *len = sizeof g_tables;
    return &g_tables;
}

/* Whose memory address p is: the slot whose range holds it (jemalloc), 0
   for the guard's own tables, else -1. */
EXPORT int cga_slot_of(const void *p)
{
    if ((uintptr_t)p - (uintptr_t)&g_tables < sizeof g_tables)
        return 0;
    uintptr_t off = (uintptr_t)p - g_region;
    return g_je && off < g_region_len ? 1 + (int)(off >> SLOT_SHIFT) : -1;
}

/* The slot's process is gone (every task of it); tcb is its main task's
   thread pointer (its context's TLS block).  The slot is quarantined for
   good when it died inside the allocator (CGA_RETIRE_QUARANTINED: its
   arena may be locked or half-updated) or, faulted, of a fault of its own
   (| CGA_RETIRE_FAULTED: a bad access or an abort is what a torn heap
   looks like, and the next process in the slot would inherit the tear);
   else its arena is consistent and the slot idle, for the next process in
   that context.  CGA_RETIRE_PY_ABANDONED: it died inside CPython's object
   allocator, whose pools of that slot start again (pyalloc.c). */
EXPORT int cga_slot_retire(int slot, char *tcb, int faulted)
{
    struct slot *sl = &slots[slot];
    int inside =
        atomic_load(&live[slot].inside) != 0 || (tcb && *(volatile int *)(tcb + g_inside_off) != 0);
    int py = py_slot_retire(slot, tcb);
    int bits = (inside ? CGA_RETIRE_QUARANTINED : 0) |
               (!inside && faulted ? CGA_RETIRE_QUARANTINED | CGA_RETIRE_FAULTED : 0) |
               (py ? CGA_RETIRE_PY_ABANDONED : 0) |
               (atomic_load(&live[slot].over_asked) ? CGA_RETIRE_OVER_BUDGET : 0);
    atomic_store(&live[slot].pid, 0);
    atomic_store(&sl->state, bits & CGA_RETIRE_QUARANTINED ? CGA_QUARANTINED : CGA_IDLE);
    return bits;
}

/* Idle slot s (no process in it; the caller keeps it so: contexts.c holds
   its context out of the pool meanwhile) has the blocks handed to it freed
   into its arenas now, by the caller, and its arenas purged, so that a dead
   node's memory the container let go of (reclaim.py) goes back to the
   kernel now, not when a next process in the slot drains it and jemalloc's
   decay gets to it.  The rule still holds: nobody else is in the slot's
   arenas, and its last process died outside them (an idle slot is not
   quarantined).  Every block is freed with no thread cache (none of the
   slot's blocks lands in the caller's).  jemalloc only: under glibc a block
   goes into the freeing thread's cache, and the big ones (mmapped) went
   back at their free.  Blocks freed, or -EBUSY (not idle), -ENOTSUP
   (glibc), -EINVAL. */
EXPORT long cga_slot_drain(int s)
{
    if (s <= 0 || s >= g_nslots)
        return -EINVAL;
    if (!g_je)
        return -ENOTSUP;
    if (atomic_load(&slots[s].state) != CGA_IDLE)
        return -EBUSY;
    long n = 0;
    uint32_t pkru = hk_open(); /* the tables, and blocks under s's key */
    void *lists[2] = {atomic_exchange(&owners[s].stack, NULL),
                      atomic_exchange(&owners[s].held, NULL)};
    for (int i = 0; i < 2; i++)
        for (void *p = lists[i], *next; p; p = next, n++) {
            next = *(void **)p;
            if (i == 0) /* counted at their drain: the held ones were */
                count_freed(s, p);
            uintptr_t *mark = mark_word(p);
            if (mark)
                *mark = 0;
            dallocx(p, JE_TCACHE_NONE);
        }
    hk_close(pkru);
    unsigned arenas[2] = {slots[s].arena, slots[s].shared_arena};
    for (int i = 0; i < 2; i++) {
        char name[40];
        snprintf(name, sizeof name, "arena.%u.purge", arenas[i]);
        mallctl(name, NULL, NULL, NULL, 0);
    }
    return n;
}

/* Slot s's memory budget, in bytes (0: none), for its process from now on
   (the host sets it before the node's construction runs). */
EXPORT int cga_slot_set_limit(int slot, uint64_t bytes)
{
    if (slot <= 0 || slot >= g_nslots)
        return -EINVAL;
    uint32_t pkru = hk_open(); /* slots[] is under the container's key */
    atomic_store(&slots[slot].limit, bytes);
    hk_close(pkru);
    return 0;
}

/* Slot s's memory in use and budget; over_*: its process went over it (and
   was ended), what it had and what it asked for; kept until the next
   process in the slot starts.  The main task's count is read from its TLS
   word while the slot's process lives, and, after its death, until the
   context's next process starts. */
EXPORT int cga_slot_memory(int slot, struct cga_slot_memory *out)
{
    if (slot <= 0 || slot >= g_nslots)
        return -EINVAL;
    out->in_use = (uint64_t)slot_bytes(slot);
    out->limit = atomic_load(&slots[slot].limit);
    out->over_used = atomic_load(&live[slot].over_used);
    out->over_asked = atomic_load(&live[slot].over_asked);
    return 0;
}

static void count_stack(struct owner *o, struct cga_slot_stats *out)
{
    for (void *p = atomic_load(&o->stack); p; p = *(void **)p) {
        out->pending_blocks++;
        out->pending_bytes += be_usable(p);
    }
    for (void *p = atomic_load(&o->held); p; p = *(void **)p) {
        out->held_blocks++;
        out->held_bytes += be_usable(p);
    }
}

/* What a slot holds.  pending_* (the blocks handed to it not taken back:
   for a quarantined slot, what has leaked) and held_* (taken back, freed at
   the next drain) are counted only while no process drains them (the slot
   is not bound). */
EXPORT int cga_slot_stats(int slot, struct cga_slot_stats *out)
{
    if (slot < 0 || slot >= g_nslots)
        return -EINVAL;
    memset(out, 0, sizeof *out);
    struct slot *sl = &slots[slot];
    out->state = atomic_load(&sl->state);
    out->pid = atomic_load(&live[slot].pid);
    out->arena = sl->arena;
    out->main_arena_allocs = atomic_load(&sl->main_allocs);
    bool walk = slot > 0 && out->state != CGA_BOUND;
    if (g_je) {
        out->handed_blocks = atomic_load(&owners[slot].handed);
        if (walk)
            count_stack(&owners[slot], out);
        return 0;
    }
    for (int i = 1; i < NOWNERS; i++) {
        if (!atomic_load(&owners[i].key) || atomic_load(&owners[i].slot) != slot)
            continue;
        out->glibc_arenas++;
        out->handed_blocks += atomic_load(&owners[i].handed);
        if (walk)
            count_stack(&owners[i], out);
    }
    return 0;
}

/* Start-up check of the glibc layout facts owner_of rests on (assumptions.py):
   a block from the main thread is main-arena; blocks a new thread allocates
   are non-main, and the first word of their aligned heap is one arena, the
   same for both, lying just past the heap header of its first heap.  The
   calling thread must be the main thread.  0 if all hold, else which
   failed (1..4). */
struct probe_arg {
    void *a, *b;
};

static void *probe_thread(void *p)
{
    struct probe_arg *pa = p;
    pa->a = __libc_malloc(GLIBC_PROBE_SIZE);
    pa->b = __libc_malloc(GLIBC_PROBE_SIZE * 3);
    return NULL;
}

EXPORT int cga_probe_glibc(void)
{
    void *m = __libc_malloc(GLIBC_PROBE_SIZE);
    int main_ok = m && !(((size_t *)m)[-1] & (GLIBC_NON_MAIN_ARENA | GLIBC_IS_MMAPPED));
    __libc_free(m);
    if (!main_ok)
        return 1;
    struct probe_arg pa = {NULL, NULL};
    pthread_t t;
    if (pthread_create(&t, NULL, probe_thread, &pa) != 0)
        return 2;
    pthread_join(t, NULL);
    int rc = 0;
    void *ar_a = pa.a ? glibc_arena_of(pa.a) : NULL;
    void *ar_b = pa.b ? glibc_arena_of(pa.b) : NULL;
    uintptr_t heap = (uintptr_t)pa.a & ~(GLIBC_HEAP_MAX - 1);
    if (!ar_a || ar_a != ar_b)
        rc = 3;
    else if ((uintptr_t)ar_a < heap || (uintptr_t)ar_a > heap + 256)
        rc = 4;
    __libc_free(pa.a);
    __libc_free(pa.b);
    return rc;
}
