/*
 * heapkeys.c - memory protection keys over node processes' native heaps:
 * part of the allocator guard (allocguard.c), jemalloc backend only.
 *
 * Its one rule:
 *
 *     A node process can write its own native heap, and no other node's.
 *
 * Every slot's jemalloc arena carves its memory (blocks and jemalloc's own
 * metadata for that arena) out of the slot's reserved address range
 * (allocguard.c).  The lower half of that range is tagged, once, with the
 * slot's key (pkey_mprotect, PROT_NONE: nothing is committed yet); the
 * arena's hooks later commit pieces with plain mprotect, which keeps the key
 * (pkeys.c checks that at start-up).  A node process runs with writes
 * disabled for every key but its own (hk_child_pkru), so a stray store into
 * another node's heap faults in the writer (SIGSEGV, SEGV_PKUERR) before
 * anything lands: the writer dies, the victim goes on.  Reads stay allowed:
 * a node may read what another node's native code gives it.  The
 * container's own threads write everything (PKRU 0).
 *
 * What every node writes legitimately must not be keyed (measured under
 * emulated PKU: each of these faulted a node that had done nothing wrong):
 *   - what the ROS stack and the interpreter allocate: Fast DDS shares its
 *     payload pools among every participant of the process (their vectors
 *     and payloads are grown by one node, written by the next), rclpy's
 *     pybind11 keeps one registry of every wrapped object (its hash nodes
 *     are linked by whichever node makes or drops an object), rcl keeps one
 *     map of rosout publishers.  A block is allocated shared when the code
 *     that asked for it (malloc's return address, or operator new's caller)
 *     lies in one of the libraries SHARED_LIBS names; everything else a
 *     node process allocates (its own native code, ctypes' calls from
 *     Python) is keyed.
 *   - Python objects: one interpreter, so reference counts, the garbage
 *     collector and thread-state links write objects any node made.  Small
 *     blocks live in pyalloc.c's region (key 0); larger ones and CPython's
 *     RAW domain go to the slot's *shared* arena, carved from the upper,
 *     untagged half of its range (cga_shared_*), never through a thread
 *     cache (so a shared block never serves a native malloc, nor the reverse).
 *   - a block freed by another slot: the freer links it onto the owner's
 *     hand-over stack through its first word (allocguard.c hand_over), with
 *     writes opened for that store alone (hk_open / hk_close).
 *   - everything not from a slot's arena: the container's heap (slot 0),
 *     stacks, TLS blocks, mmaps, libraries' data: key 0.
 *
 * Keys are allocated in the constructor below, on the main thread before
 * any other thread exists: pkey_alloc opens a new key only in the calling
 * thread's PKRU, and every later thread starts with its creator's (pkeys.c
 * checks that too), so all container threads write every key.  Node
 * processes are clone()d from container threads and set their own PKRU
 * first thing (cga_child_start).  Signal handlers run with the kernel's
 * default PKRU (every key but 0 access-disabled): what a handler of a node
 * process touches (its control block, TLS, stacks, Python frames and code)
 * is all key 0 or shared.
 *
 * The guard's own tables (allocguard.c struct tables: every slot's state,
 * arena, hooks and the owners' hand-over stacks) are under one more key,
 * the container's (hk_tag_tables), which node processes may not write: the
 * only stores a node process makes into them (handing a block over,
 * draining its stack) are bracketed by hk_open / hk_close.  What a node's
 * tasks write on every malloc (the count inside, the carve pointers) is in
 * allocguard.c's live[], outside the tables, under no key.
 *
 * More slots than keys (x86_64 has 15, one of them the tables'): slot s
 * uses node key (s-1) % nkeys, and a new context takes an unused slot of
 * the key the fewest live slots hold (allocguard.c, pick_unused_slot), so up
 * to 14 live node processes
 * (pooled contexts count) have a key each; past that, nodes that share a key
 * are not protected from each other, only from the rest.  Turned on by CLONEGUARD_PKEYS=1 in the
 * environment (the container's --pkeys sets it when it re-executes itself with the guard).
 */
#define _GNU_SOURCE
#include <cpuid.h>
#include <link.h>
#include <stdatomic.h>
#include <errno.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>

#include "allocguard.h"
#include "guard_internal.h"

#define EXPORT __attribute__((visibility("default")))
#define MAX_KEYS 15

static int g_keys[MAX_KEYS];
static int g_nkeys;      /* node heaps' keys */
static int g_tables_key; /* the guard's tables' (0: none) */
static int g_errno;      /* why there are none, if asked for */
static int g_wanted;

static inline uint32_t rdpkru(void)
{
    uint32_t eax, edx;
    __asm__ volatile(".byte 0x0f, 0x01, 0xee" : "=a"(eax), "=d"(edx) : "c"(0));
    return eax;
}

static inline void wrpkru(uint32_t v)
{
    __asm__ volatile(".byte 0x0f, 0x01, 0xef" : : "a"(v), "c"(0), "d"(0) : "memory");
}

/* Before pyalloc.c's constructor (which asks hk_enabled), before main. */
__attribute__((constructor(101))) static void hk_init(void)
{
    const char *want = getenv("CLONEGUARD_PKEYS");
    if (!want || strcmp(want, "1") != 0)
        return;
    g_wanted = 1;
    unsigned a, b, c, d;
    if (!__get_cpuid_count(7, 0, &a, &b, &c, &d) || !((c >> 4) & 1)) {
        g_errno = ENOSYS; /* no PKU, or not enabled (OSPKE) */
        return;
    }
    while (g_nkeys < MAX_KEYS) {
        int k = pkey_alloc(0, 0); /* open in this thread's PKRU */
        if (k < 0) {
            g_errno = errno;
            break;
        }
        g_keys[g_nkeys++] = k;
    }
    if (g_nkeys)
        g_errno = 0;
    if (g_nkeys >= 2)
        g_tables_key = g_keys[--g_nkeys];
}

HIDDEN int hk_enabled(void)
{
    return g_nkeys > 0;
}

HIDDEN int hk_key_of_slot(int slot)
{
    return slot > 0 && g_nkeys ? g_keys[(slot - 1) % g_nkeys] : 0;
}

/* The PKRU of slot s's tasks: writes to every key but its own disabled. */
static uint32_t slot_pkru(int slot)
{
    uint32_t v = 0;
    int mine = hk_key_of_slot(slot);
    for (int i = 0; i < g_nkeys; i++)
        if (g_keys[i] != mine)
            v |= (uint32_t)PKEY_DISABLE_WRITE << (2 * g_keys[i]);
    if (g_tables_key)
        v |= (uint32_t)PKEY_DISABLE_WRITE << (2 * g_tables_key);
    return v;
}

/* Tag [base, base + len) with slot s's key; its pages stay uncommitted. */
HIDDEN int hk_tag(uintptr_t base, size_t len, int slot)
{
    if (!g_nkeys)
        return 0;
    return pkey_mprotect((void *)base, len, PROT_NONE, hk_key_of_slot(slot)) == 0 ? 0 : -errno;
}

/* The guard's tables (allocguard.c struct tables, page-aligned): under the
   container's key, which no node process may write. */
HIDDEN int hk_tag_tables(void *addr, size_t len)
{
    if (!g_tables_key)
        return 0;
    return pkey_mprotect(addr, len, PROT_READ | PROT_WRITE, g_tables_key) == 0 ? 0 : -errno;
}

/* First thing in a node process's main task; its threads inherit it. */
HIDDEN void hk_child_enter(int slot)
{
    if (g_nkeys)
        wrpkru(slot_pkru(slot));
}

/* Around one legitimate store into another slot's heap. */
HIDDEN uint32_t hk_open(void)
{
    if (!g_nkeys)
        return 0;
    uint32_t was = rdpkru();
    if (was)
        wrpkru(0);
    return was;
}

HIDDEN void hk_close(uint32_t was)
{
    if (was)
        wrpkru(was);
}

/* For the container: keys in use (0: off), or -errno why --pkeys cannot be
   (-ENOSYS: no PKU; -ENOSPC and others: pkey_alloc's), or -ENOENT if they
   were not asked for. */
EXPORT int cga_pkeys(int *keys, int max)
{
    if (!g_wanted)
        return -ENOENT;
    if (!g_nkeys)
        return -(g_errno ? g_errno : ENOSPC);
    for (int i = 0; i < g_nkeys && i < max; i++)
        keys[i] = g_keys[i];
    return g_nkeys;
}

/* The key the guard's tables are under (0: none). */
EXPORT int cga_tables_key(void)
{
    return g_tables_key;
}

/* The key slot s's heap is tagged with (0: none). */
EXPORT int cga_slot_key(int slot)
{
    return hk_key_of_slot(slot);
}

/* ---------------------------------------------------------------------- */
/* Which callers get shared memory: the text of these libraries (a prefix
   of the file's name, or "rosidl" anywhere in it: generated message
   support).  The main program (the interpreter) is one of them. */

static const char *const SHARED_LIBS[] = {
    "libc.so",
    "ld-linux",
    "libstdc++",
    "libgcc_s",
    "libm.so",
    "libpython",
    "libjemalloc",
    "libfastrtps",
    "libfastcdr",
    "libfoonathan",
    "libtinyxml2",
    "libssl",
    "libcrypto",
    "librcl",
    "librmw",
    "librcutils",
    "librcpputils",
    "librosidl",
    "libtracetools",
    "libspdlog",
    "libyaml",
    "libament_index",
    "libclass_loader",
    "libconsole_bridge",
    "_rclpy",
    "_clonecore",
    "_rclglue",
    "_allocguard",
    "_robust",
    "_pylocks",
    "_pybind11_registry",
};

struct range {
    uintptr_t lo, hi;
};
struct table {
    int n;
    struct range r[];
};
#define MAX_RANGES 4096

static _Atomic(struct table *) g_shared; /* published whole, never freed */

static int shared_name(const char *path)
{
    if (!*path)
        return 1; /* the main program */
    const char *base = strrchr(path, '/');
    base = base ? base + 1 : path;
    if (strstr(base, "rosidl"))
        return 1;
    for (size_t i = 0; i < sizeof SHARED_LIBS / sizeof SHARED_LIBS[0]; i++)
        if (strncmp(base, SHARED_LIBS[i], strlen(SHARED_LIBS[i])) == 0)
            return 1;
    return 0;
}

static int add_object(struct dl_phdr_info *info, size_t size, void *arg)
{
    (void)size;
    struct table *t = arg;
    if (!shared_name(info->dlpi_name ? info->dlpi_name : ""))
        return 0;
    for (int i = 0; i < info->dlpi_phnum && t->n < MAX_RANGES; i++) {
        const ElfW(Phdr) *ph = &info->dlpi_phdr[i];
        if (ph->p_type == PT_LOAD && (ph->p_flags & PF_X))
            t->r[t->n++] = (struct range){info->dlpi_addr + ph->p_vaddr,
                                          info->dlpi_addr + ph->p_vaddr + ph->p_memsz};
    }
    return 0;
}

static int by_lo(const void *a, const void *b)
{
    uintptr_t x = ((const struct range *)a)->lo, y = ((const struct range *)b)->lo;
    return x < y ? -1 : x > y;
}

/* On a container thread, before each node process starts: the libraries
   loaded now (rebuilt only when one was loaded since).  One a node process loads itself is not in
   the table until the next node process starts (its allocations are keyed meanwhile). */
static int read_adds(struct dl_phdr_info *info, size_t size, void *arg)
{
    (void)size;
    *(unsigned long long *)arg = info->dlpi_adds;
    return 1; /* the first object tells */
}

HIDDEN void hk_refresh_shared(void)
{
    static unsigned long long seen; /* container threads: one at a time */
    unsigned long long adds = 0;
    dl_iterate_phdr(read_adds, &adds);
    if (adds == seen && atomic_load(&g_shared))
        return; /* nothing loaded since */
    seen = adds;
    size_t len = sizeof(struct table) + MAX_RANGES * sizeof(struct range);
    struct table *t = mmap(NULL, len, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (t == MAP_FAILED)
        return;
    t->n = 0;
    dl_iterate_phdr(add_object, t);
    qsort(t->r, (size_t)t->n, sizeof t->r[0], by_lo);
    struct table *old = atomic_exchange(&g_shared, t);
    (void)old; /* a node process may still read it */
}

/* Per thread, the answers for the last few callers, each with the table it
   came from: a table is never freed or changed once published, so an entry
   from an older one is recognised by its pointer and looked up again.
   Nearly all of a node process's allocating comes from a handful of call
   sites (the interpreter's, rcl's, Fast DDS's), so most calls find theirs
   here instead of searching the table (every malloc asks). */
#define CALLER_CACHE 8
static __thread struct {
    const void *pc;
    const struct table *t;
    int shared;
} t_callers[CALLER_CACHE] __attribute__((tls_model("initial-exec")));

static int search(const struct table *t, uintptr_t a)
{
    int lo = 0, hi = t->n - 1;
    while (lo <= hi) {
        int mid = (lo + hi) / 2;
        if (a < t->r[mid].lo)
            hi = mid - 1;
        else if (a >= t->r[mid].hi)
            lo = mid + 1;
        else
            return 1;
    }
    return 0;
}

HIDDEN int hk_shared_caller(const void *pc)
{
    const struct table *t = atomic_load_explicit(&g_shared, memory_order_acquire);
    if (!t)
        return 0;
    unsigned i = (unsigned)((uintptr_t)pc >> 2) % CALLER_CACHE;
    if (t_callers[i].pc == pc && t_callers[i].t == t)
        return t_callers[i].shared;
    int shared = search(t, (uintptr_t)pc);
    t_callers[i].pc = pc;
    t_callers[i].t = t;
    t_callers[i].shared = shared;
    return shared;
}
