/*
 * guard_internal.h - what the allocator guard's two files share: allocguard.c
 * (malloc) and pyalloc.c (CPython's object allocator).  Hidden: nothing here
 * is visible outside the guard's shared library.
 */
#ifndef CLONEGUARD_GUARD_INTERNAL_H
#define CLONEGUARD_GUARD_INTERNAL_H

#include <stdatomic.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#define HIDDEN __attribute__((visibility("hidden")))

/* allocguard.c: the calling task's slot (0: the container, or before the
   guard is active), and whether it is a node process's main task whose
   allocator calls are bracketed by a TLS word rather than its slot's
   counter. */
HIDDEN int cga_caller_slot(void);
HIDDEN int cga_caller_bound(void);

/* pyalloc.c: slot s's process is gone (tcb: its main task's thread
   pointer); 1 if it died inside CPython's object allocator (its pools are
   abandoned, a new generation starts), else 0. */
HIDDEN int py_slot_retire(int s, char *tcb);

/* allocguard.c: memory every node process may write (heapkeys.c): from
   the calling slot's shared arena when protection keys are on, else plain
   malloc.  Freed with free(). */
HIDDEN void *cga_shared_alloc(size_t n, bool zero);
HIDDEN void *cga_shared_realloc(void *p, size_t n);

/* allocguard.c: the slot bound to process pid, 0 if none (a scan:
   async-signal-safe). */
HIDDEN int cga_slot_of_pid(int pid);
/* stops.c: the test rig's stop points (CGA_STOP_*, allocguard.h).  Every
   place calls cga_stop_point; it costs one load while nothing is armed. */
extern HIDDEN _Atomic int cga_stops_armed;
HIDDEN void cga_stop_passed(int s, int place);
HIDDEN void stops_clear(int s);
static inline void cga_stop_point(int s, int place)
{
    if (__builtin_expect(atomic_load_explicit(&cga_stops_armed, memory_order_relaxed), 0))
        cga_stop_passed(s, place);
}
/* bigblocks.c: which slot got each of glibc's mmapped blocks. */
HIDDEN bool bb_put(const void *p, int slot); /* false: table full */
HIDDEN int bb_take(const void *p);           /* its slot, -1: not known */
/* pyalloc.c: bytes of Python's small objects slot s has in use. */
HIDDEN long py_slot_bytes(int s);
/* --core-dumps: the pools' never-used tail out of dumps (1) or back (0). */
HIDDEN int py_dump_tail(int exclude);
HIDDEN void py_slot_begin(int s); /* a new process: from 0 */
/* allocguard.c: slot s is over its memory budget if it gets n bytes more:
   then its process is ended there (SIGKILL to itself), the figures left
   for cga_slot_memory.  Called outside the allocator's bracket. */
HIDDEN void cga_within_budget(int s, size_t n);
/* heapkeys.c: protection keys over node processes' native heaps. */
HIDDEN int hk_enabled(void); /* keys were allocated */
HIDDEN int hk_key_of_slot(int slot);
HIDDEN int hk_tag(uintptr_t base, size_t len, int slot); /* 0, or -errno */
HIDDEN int hk_tag_tables(void *addr, size_t len);        /* 0, or -errno */
HIDDEN void hk_child_enter(int slot);                    /* the node process's PKRU */
HIDDEN uint32_t hk_open(void);                           /* every key writable ... */
HIDDEN void hk_close(uint32_t was);                      /* ... and back */
HIDDEN void hk_refresh_shared(void);                     /* which callers get shared blocks */
HIDDEN int hk_shared_caller(const void *pc);

#endif
