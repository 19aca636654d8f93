/*
 * stops.c - stop points: a node process stops itself (SIGSTOP, its whole
 * thread group) at a chosen kind of place, when the test rig asks, so that
 * a kill from outside lands exactly there.  The test rig's seam
 * (container/seams.py): a container started without CLONEGUARD_STOP_SIGNAL,
 * or without the rig installed, never installs the handler below.
 *
 * The places (CGA_STOP_*, allocguard.h):
 *   ALLOCATION     the guard's malloc, inside its bracket (counted inside the
 *                  allocator: a death there quarantines the slot)
 *   PY_ALLOCATION  CPython's object allocator (pyalloc.c), a block taken from
 *                  a pool and the pool's count not yet updated; the caller
 *                  holds the GIL
 *   PY_LOCK        a Python lock just acquired (pylocks.c); the caller holds
 *                  the lock and the GIL
 *
 * The request is a sigqueue(2) of the stop signal to the node process, its
 * value CGA_STOP_REQUEST(place, n): stop at the n-th time any of its tasks
 * passes such a place from now (n = 0: forget an earlier request); for
 * PY_LOCK the high 32 bits may hold the key of one lock's name, and only
 * that lock's acquires count (pylocks.c asks cga_stop_lock_key and its
 * name hook whether the lock it took is that one).  The
 * handler runs on whichever task of the process takes the signal, and so
 * finds the slot by the process's pid, not by its TLS.  Each slot holds one
 * request; a new process in a slot starts with none (stops_clear).
 */
#define _GNU_SOURCE
#include <signal.h>
#include <stdatomic.h>
#include <stdint.h>
#include <sys/syscall.h>
#include <unistd.h>

#include "allocguard.h"
#include "guard_internal.h"

#define EXPORT __attribute__((visibility("default")))

static struct {
    _Atomic int place;    /* CGA_STOP_*, 0: none */
    _Atomic int left;     /* passes before the stop */
    _Atomic uint32_t key; /* PY_LOCK: the lock's key, 0: any */
} g_stop[CGA_NSLOTS];

/* Slots with a request: every place's check is one load of this while 0. */
HIDDEN _Atomic int cga_stops_armed;

/* Slot s's request, if any, forgotten. */
HIDDEN void stops_clear(int s)
{
    if (atomic_exchange(&g_stop[s].place, 0) != 0)
        atomic_fetch_sub(&cga_stops_armed, 1);
}

/* The stop signal's handler in a node process (child.c installs it).
   Async-signal-safe: loads, stores and getpid. */
EXPORT void cga_stop_request(int sig, siginfo_t *si, void *uc)
{
    (void)sig;
    (void)uc;
    if (si->si_code != SI_QUEUE) /* a plain kill: not a request */
        return;
    int s = cga_slot_of_pid((int)syscall(SYS_getpid));
    if (s <= 0)
        return;
    uint64_t value = (uint64_t)(uintptr_t)si->si_value.sival_ptr;
    int v = (int)(uint32_t)value;
    int place = CGA_STOP_PLACE(v), n = CGA_STOP_COUNT(v);
    stops_clear(s);
    if (n <= 0 || place < CGA_STOP_ALLOCATION || place > CGA_STOP_PY_LOCK)
        return;
    atomic_store(&g_stop[s].key, (uint32_t)(value >> CGA_STOP_KEY_SHIFT));
    atomic_store(&g_stop[s].left, n);
    atomic_store(&g_stop[s].place, place);
    atomic_fetch_add(&cga_stops_armed, 1);
}

HIDDEN void cga_stop_passed(int s, int place)
{
    if (s <= 0 || atomic_load(&g_stop[s].place) != place)
        return;
    if (atomic_fetch_sub(&g_stop[s].left, 1) != 1)
        return;
    if (atomic_exchange(&g_stop[s].place, 0) != place)
        return; /* another task got there first */
    atomic_fetch_sub(&cga_stops_armed, 1);
    /* To this task, not the process: a process-directed SIGSTOP wakes one
       task (the main one, if it can take it) to start the group stop, and
       the caller would run on out of the place meanwhile.  Sent to itself,
       the caller takes it as the kill returns, and stops here; the stop is
       still its whole process's. */
    syscall(SYS_tgkill, syscall(SYS_getpid), syscall(SYS_gettid), SIGSTOP);
}

/* For pylocks.c, a module of its own: the flag its every acquire loads
   (nothing more while no request is armed), and its place, for the
   caller's slot. */
EXPORT _Atomic int *cga_stops_armed_flag(void)
{
    return &cga_stops_armed;
}

EXPORT void cga_stop_here(int place)
{
    cga_stop_passed(cga_caller_slot(), place);
}

/* For pylocks.c: -1 when the caller's process has no PY_LOCK request, else
   the key of the one lock it names (0: any lock). */
EXPORT int64_t cga_stop_lock_key(void)
{
    int s = cga_caller_slot();
    if (s <= 0 || atomic_load(&g_stop[s].place) != CGA_STOP_PY_LOCK)
        return -1;
    return atomic_load(&g_stop[s].key);
}
