/*
 * allocguard.h - the allocator guard's control interface (allocguard.c).
 *
 * The guard is a small malloc interposer preloaded (LD_PRELOAD) into an
 * isolated container.  The container finds these functions with dlsym; a
 * process without the guard preloaded simply has none of them.  Only
 * clonecore.c calls them (from container threads, the monitor, and a child
 * right after it starts).
 */
#ifndef CLONEGUARD_ALLOCGUARD_H
#define CLONEGUARD_ALLOCGUARD_H

#include <signal.h>
#include <stddef.h>
#include <stdint.h>

/* A slot is one node process's allocator identity: its arena(s) and the
   stack of blocks others freed for it.  Slot 0 is the container.  (Between
   the cdef markers: what the core's Python sees too, core.h.) */
/* cdef: begin */
enum {
    CGA_UNUSED = 0,      /* never handed out */
    CGA_IDLE = 1,        /* set up, no process in it (pooled) */
    CGA_BOUND = 2,       /* a node process allocates from it */
    CGA_QUARANTINED = 3, /* its process died inside the allocator (its
                            arena(s) may be locked or torn) or of a
                            fault of its own (may be torn): for good */
};

/* Slots a container has: slot 0 and up to CGA_NSLOTS - 1 node processes. */
#define CGA_NSLOTS 512

/* Stop points (stops.c; the test rig's seam): the places a node process
   can be asked to stop itself at, and the request's sigqueue value. */
#define CGA_STOP_ALLOCATION 1    /* the guard's malloc, inside its bracket */
#define CGA_STOP_PY_ALLOCATION 2 /* CPython's object allocator, GIL held */
#define CGA_STOP_PY_LOCK 3       /* a Python lock just acquired, GIL held */
#define CGA_STOP_PLACE_BITS 4    /* the request's low bits: the place */
#define CGA_STOP_REQUEST(place, n) ((place) | ((n) << CGA_STOP_PLACE_BITS))
#define CGA_STOP_PLACE(v) ((v) & ((1 << CGA_STOP_PLACE_BITS) - 1))
#define CGA_STOP_COUNT(v) ((v) >> CGA_STOP_PLACE_BITS)
/* A PY_LOCK request's value may name one lock: its key (seams.py's
   stop_lock_key of the lock's name, never 0) in the value's high 32 bits
   (sigqueue's value is a pointer: 64 bits here). 0 there: any lock. */
#define CGA_STOP_KEY_SHIFT 32

/* What cga_slot_retire returns: the bits of what a dead process left. */
#define CGA_RETIRE_QUARANTINED 1 /* died inside malloc: slot quarantined */
/* died inside CPython's object allocator (pyalloc.c): its pools abandoned */
#define CGA_RETIRE_PY_ABANDONED 2
/* died of a fault of its own: slot quarantined (with _QUARANTINED) */
#define CGA_RETIRE_FAULTED 4
/* ended itself over its memory budget (cga_slot_memory says how far) */
#define CGA_RETIRE_OVER_BUDGET 8

/* A slot's memory in use (allocguard.c: what is counted) and budget. */
struct cga_slot_memory {
    uint64_t in_use;     /* bytes */
    uint64_t limit;      /* its budget, 0: none */
    uint64_t over_used;  /* it went over: what it had in use then ... */
    uint64_t over_asked; /* ... and what it asked for (0: it did not) */
};

/* CPython's object allocator of one slot (pyalloc.c). */
struct cga_py_stats {
    unsigned generation; /* bumped each time its pools were abandoned */
    uint64_t pools;      /* pools it ever took from the region */
    uint64_t handed;     /* blocks others freed and handed to it */
    uint64_t dropped;    /* frees into abandoned pools, left undone */
    uint64_t abandoned;  /* times its process died inside */
};

struct cga_slot_stats {
    int state;               /* CGA_* */
    int pid;                 /* the process bound to it, 0 if none */
    unsigned arena;          /* jemalloc arena index (jemalloc backend) */
    int glibc_arenas;        /* glibc arenas attributed to it */
    uint64_t handed_blocks;  /* blocks others freed and handed to it */
    uint64_t pending_blocks; /* ... not taken back by their owner yet */
    uint64_t pending_bytes;
    uint64_t held_blocks; /* ... taken back, to be freed at its next drain */
    uint64_t held_bytes;
    uint64_t main_arena_allocs; /* glibc: blocks it got from the container's
                                   main arena (a fallback glibc makes) */
};
/* cdef: end */

/* The functions the guard exports (allocguard.c, pyalloc.c, heapkeys.c,
   stops.c define them; nothing links against them: the container and the
   test rig find them with dlsym or ctypes). */
const char *cga_backend(void);
int cga_activate(int container_pid);
int cga_slot_new(void);
int cga_warm(int slot);
void cga_slot_bind(int slot);
void cga_child_start(void);
const void *cga_tables(size_t *len);
int cga_slot_of(const void *p);
int cga_slot_retire(int slot, char *tcb, int faulted);
long cga_slot_drain(int slot);
int cga_slot_set_limit(int slot, uint64_t bytes);
int cga_slot_memory(int slot, struct cga_slot_memory *out);
int cga_slot_stats(int slot, struct cga_slot_stats *out);
int cga_probe_glibc(void);
int cga_py_abandon(int s);
int cga_py_abandoned(const void *p);
int cga_py_owner(const void *p);
int cga_py_active(void);
int cga_dump_exclude(int exclude);
int cga_py_stats(int s, struct cga_py_stats *out);
long cga_py_drain(int s);
int cga_pkeys(int *keys, int max);
int cga_tables_key(void);
int cga_slot_key(int slot);
void cga_stop_request(int sig, siginfo_t *si, void *uc);
_Atomic int *cga_stops_armed_flag(void);
void cga_stop_here(int place);
int64_t cga_stop_lock_key(void);

/* The functions, as clonecore.c calls them (through dlsym). */
typedef int (*cga_activate_fn)(int container_pid);
typedef const char *(*cga_backend_fn)(void);
typedef int (*cga_slot_new_fn)(void);
typedef int (*cga_warm_fn)(int slot);
typedef void (*cga_slot_bind_fn)(int slot);
typedef void (*cga_child_start_fn)(void);
typedef int (*cga_slot_retire_fn)(int slot, char *tcb, int faulted);
typedef int (*cga_slot_stats_fn)(int slot, struct cga_slot_stats *out);
typedef int (*cga_py_stats_fn)(int slot, struct cga_py_stats *out);
typedef int (*cga_py_owner_fn)(const void *p);
typedef int (*cga_py_active_fn)(void);
typedef int (*cga_py_abandon_fn)(int slot);
typedef int (*cga_py_abandoned_fn)(const void *p);
typedef long (*cga_py_drain_fn)(int slot);
typedef long (*cga_slot_drain_fn)(int slot);
typedef int (*cga_dump_exclude_fn)(int exclude);
typedef int (*cga_pkeys_fn)(int *keys, int max);
typedef int (*cga_slot_of_fn)(const void *p);
typedef int (*cga_slot_set_limit_fn)(int slot, uint64_t bytes);
typedef int (*cga_slot_memory_fn)(int slot, struct cga_slot_memory *out);
/* stops.c: the stop signal's handler, in a node process. */
typedef void (*cga_stop_request_fn)(int sig, siginfo_t *si, void *uc);

#endif
