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
 * What every node writes legitimately must not be keyed:
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
 * More slots than keys (x86_64 has 15): slot s uses key 1 + (s-1) % nkeys,
 * so nodes that share a key are not protected from each other, only from
 * the rest.  Turned on by CLONEGUARD_PKEYS=1 in the environment (the
 * container's --pkeys sets it when it re-executes itself with the guard).
 */
#define _GNU_SOURCE
#include <cpuid.h>
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
static int g_nkeys;
static int g_errno;                     /* why there are none, if asked for */
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
        g_errno = ENOSYS;               /* no PKU, or not enabled (OSPKE) */
        return;
    }
    while (g_nkeys < MAX_KEYS) {
        int k = pkey_alloc(0, 0);       /* open in this thread's PKRU */
        if (k < 0) {
            g_errno = errno;
            break;
        }
        g_keys[g_nkeys++] = k;
    }
    if (g_nkeys)
        g_errno = 0;
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
    return v;
}

/* Tag [base, base + len) with slot s's key; its pages stay uncommitted. */
HIDDEN int hk_tag(uintptr_t base, size_t len, int slot)
{
    if (!g_nkeys)
        return 0;
    return pkey_mprotect((void *)base, len, PROT_NONE, hk_key_of_slot(slot)) == 0 ? 0 : -errno;
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

/* The key slot s's heap is tagged with (0: none). */
EXPORT int cga_slot_key(int slot)
{
    return hk_key_of_slot(slot);
}
