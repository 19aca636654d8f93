/*
 * bigblocks.c - who allocated each of glibc's mmapped blocks, for the
 * allocator guard's count of each node process's memory (allocguard.c).
 *
 * A block glibc serves with its own mmap (requests over the fixed mmap
 * threshold, 128 KiB: container/allocator.py) belongs to no arena, so the
 * guard cannot tell from the block whose it is, and anyone frees it
 * directly (munmap takes no lock).  This table remembers the slot that got
 * each such block: bb_put when it is handed out, bb_take when it is freed
 * (or reallocated), by whoever frees it.
 *
 * Lock-free, because a node process can be SIGKILLed anywhere in it and no
 * other may ever wait for it: open addressing on the block's address, a
 * claim is one CAS of its key word.  A freed entry becomes a tombstone that
 * a later bb_put may claim again, so the table never fills with them; a
 * lookup probes past tombstones up to an empty word.  An address is in the
 * table at most once (a block is not handed out twice while in use).  A
 * process that dies between the CAS and storing the slot leaves an entry
 * whose slot reads 0 (the container's: not counted against any node).  When
 * the table is full the block is not remembered: bb_put returns false and
 * the caller counts it nowhere (BB_SIZE blocks of 128 KiB and more is
 * 128 GiB: a machine runs out first).
 */
#define _GNU_SOURCE
#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>

#include "guard_internal.h"

/* entries: 16 MiB of address space, paged in as used */
#define BB_SIZE (1u << 20)
#define BB_EMPTY ((uintptr_t)0)
#define BB_TOMB ((uintptr_t)1) /* no block is at address 1 */

static struct {
    _Atomic uintptr_t key; /* the block's address */
    _Atomic int slot;
} g_bb[BB_SIZE];

static inline uint32_t bb_home(const void *p)
{
    return (uint32_t)(((uintptr_t)p >> 12) * 0x9e3779b97f4a7c15ull >> 44) & (BB_SIZE - 1);
}

HIDDEN bool bb_put(const void *p, int slot)
{
    uint32_t i = bb_home(p);
    for (uint32_t n = 0; n < BB_SIZE; n++, i = (i + 1) & (BB_SIZE - 1)) {
        uintptr_t k = atomic_load_explicit(&g_bb[i].key, memory_order_relaxed);
        if ((k == BB_EMPTY || k == BB_TOMB) &&
            atomic_compare_exchange_strong(&g_bb[i].key, &k, (uintptr_t)p)) {
            atomic_store_explicit(&g_bb[i].slot, slot, memory_order_release);
            return true;
        }
    }
    return false;
}

/* The slot that got block p, its entry removed; -1 if it is not in the table. */
HIDDEN int bb_take(const void *p)
{
    uint32_t i = bb_home(p);
    for (uint32_t n = 0; n < BB_SIZE; n++, i = (i + 1) & (BB_SIZE - 1)) {
        uintptr_t k = atomic_load_explicit(&g_bb[i].key, memory_order_acquire);
        if (k == BB_EMPTY)
            return -1;
        if (k == (uintptr_t)p) {
            int slot = atomic_exchange_explicit(&g_bb[i].slot, 0, memory_order_acquire);
            atomic_store_explicit(&g_bb[i].key, BB_TOMB, memory_order_release);
            return slot;
        }
    }
    return -1;
}
