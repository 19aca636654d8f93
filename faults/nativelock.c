/* nativelock.c - native locks of a C extension that every node process of
 * an isolated container shares (the extension is loaded once, into the one
 * address space), and ways to die holding them: what the lock doctor
 * (container/isolated/clonecore/mutexes.c) is tested against.  A test extension of the
 * rig, like gilfault.c.
 *
 * g_locks holds one mutex of each kind: NORMAL (as std::mutex), RECURSIVE
 * (std::recursive_mutex), ERRORCHECK, ADAPTIVE and a robust NORMAL; g_file
 * is a stdio stream, whose lock is one of glibc's internal ones; g_rwlock a
 * rwlock (as std::shared_mutex).  A waiter takes a mutex by
 * pthread_mutex_lock, by pthread_mutex_timedlock or _clocklock in a loop of
 * 0.2 s tries (as std::timed_mutex::try_lock_for in a loop), or as the
 * relock after a pthread_cond_timedwait or _clockwait that times out.  cffi
 * releases the GIL around every call, so a caller blocked here holds no
 * Python state. */
#define _GNU_SOURCE
#include <errno.h>
#include <pthread.h>
#include <stdbool.h>
#include <signal.h>
#include <stdio.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include "nativelock.h"

static pthread_mutex_t g_locks[NL_KINDS];
static FILE *g_file;
static pthread_rwlock_t g_rwlock = PTHREAD_RWLOCK_INITIALIZER;
static pthread_cond_t g_cond = PTHREAD_COND_INITIALIZER; /* never signalled */
static int g_in_cond_wait[NL_KINDS];                     /* written holding g_locks[kind] */

__attribute__((constructor)) static void nativelock_init(void)
{
    static const int types[NL_KINDS] = {PTHREAD_MUTEX_NORMAL, PTHREAD_MUTEX_RECURSIVE,
                                        PTHREAD_MUTEX_ERRORCHECK, PTHREAD_MUTEX_ADAPTIVE_NP,
                                        PTHREAD_MUTEX_NORMAL};
    for (int k = 0; k < NL_KINDS; k++) {
        pthread_mutexattr_t at;
        pthread_mutexattr_init(&at);
        if (k != NL_NORMAL) /* NORMAL as PTHREAD_MUTEX_INITIALIZER makes it */
            pthread_mutexattr_settype(&at, types[k]);
        if (k == NL_ROBUST)
            pthread_mutexattr_setrobust(&at, PTHREAD_MUTEX_ROBUST);
        pthread_mutex_init(&g_locks[k], &at);
        pthread_mutexattr_destroy(&at);
    }
    g_file = fopen("/dev/null", "w");
}

static int bad(int kind)
{
    return kind < 0 || kind >= NL_KINDS;
}

static _Noreturn void die(int how)
{
    if (how == NL_SEGFAULT)
        *(volatile int *)0 = 0;
    kill(getpid(), SIGKILL);
    for (;;)
        pause();
}

/* Lock and unlock once: 0, 1 if the lock came with EOWNERDEAD (robust; made
   consistent), -errno on error. */
int nativelock_use(int kind)
{
    if (bad(kind))
        return -EINVAL;
    int r = pthread_mutex_lock(&g_locks[kind]), repaired = 0;
    if (r == EOWNERDEAD) {
        pthread_mutex_consistent(&g_locks[kind]);
        repaired = 1;
    } else if (r) {
        return -r;
    }
    pthread_mutex_unlock(&g_locks[kind]);
    return repaired;
}

/* Take it (a recursive one twice) and die. */
int nativelock_hold_and_die(int kind, int how)
{
    if (bad(kind))
        return -EINVAL;
    pthread_mutex_lock(&g_locks[kind]);
    if (kind == NL_RECURSIVE)
        pthread_mutex_lock(&g_locks[kind]);
    die(how);
}

/* Take it (a recursive one twice) and die once a task has blocked on it:
   pthread_mutex_lock and its timed forms write 2 into the lock word before
   they sleep on it.  Looks every 1 ms. */
int nativelock_hold_and_die_once_waited(int kind, int how)
{
    if (bad(kind) || kind == NL_ROBUST)
        return -EINVAL;
    pthread_mutex_lock(&g_locks[kind]);
    if (kind == NL_RECURSIVE)
        pthread_mutex_lock(&g_locks[kind]);
    while (__atomic_load_n(&g_locks[kind].__data.__lock, __ATOMIC_ACQUIRE) < 2)
        usleep(1000);
    die(how);
}

/* Die half-way through pthread_mutex_lock: the lock word taken (its first
   step), the owner not written yet (its next). */
int nativelock_die_taking(int kind, int how)
{
    if (bad(kind) || kind == NL_ROBUST)
        return -EINVAL;
    int unlocked = 0;
    if (!__atomic_compare_exchange_n(&g_locks[kind].__data.__lock, &unlocked, 1, false,
                                     __ATOMIC_ACQUIRE, __ATOMIC_RELAXED))
        return -EBUSY;
    die(how);
}

int nativelock_hold(int kind)
{
    return bad(kind) ? -EINVAL : -pthread_mutex_lock(&g_locks[kind]);
}

int nativelock_release(int kind)
{
    return bad(kind) ? -EINVAL : -pthread_mutex_unlock(&g_locks[kind]);
}

static void *exit_holding(void *p)
{
    pthread_mutex_lock(p);
    return NULL; /* a thread that ends holding it */
}

/* A thread of the caller's process takes it and ends: its owner is gone,
   and was never a dead node's. */
int nativelock_thread_exits_holding(int kind)
{
    if (bad(kind) || kind == NL_ROBUST)
        return -EINVAL;
    pthread_t t;
    int r = pthread_create(&t, NULL, exit_holding, &g_locks[kind]);
    return r ? -r : -pthread_join(t, NULL);
}

/* Hold the stream's lock (glibc's own, recording no owner tid) and die. */
int nativelock_die_holding_file(int how)
{
    if (!g_file)
        return -ENOENT;
    flockfile(g_file);
    die(how);
}

int nativelock_use_file(void)
{
    if (!g_file)
        return -ENOENT;
    fputs("beat\n", g_file);
    return 0;
}

long nativelock_address(int kind)
{
    return bad(kind) ? 0 : (long)&g_locks[kind];
}

/* clock's now + ms */
static struct timespec in_ms(clockid_t clock, long ms)
{
    struct timespec t;
    clock_gettime(clock, &t);
    t.tv_nsec += ms * 1000000L;
    t.tv_sec += t.tv_nsec / 1000000000L;
    t.tv_nsec %= 1000000000L;
    return t;
}

/* Take g_locks[kind] as `way` says, and give it back: as nativelock_use.
   A timed try that times out is tried again (0.2 s each); a condvar wait
   (20 ms, never signalled) ends in the relock; a trylock that finds it
   held is tried again after 1 ms (std::mutex::try_lock in a loop: it never
   blocks). */
int nativelock_use_by(int kind, int way)
{
    if (bad(kind) || way < 0 || way >= NL_WAYS)
        return -EINVAL;
    pthread_mutex_t *m = &g_locks[kind];
    if (way == NL_LOCK)
        return nativelock_use(kind);
    int r, repaired = 0;
    if (way == NL_TRYLOCK) {
        struct timespec ms = {0, 1000000L};
        while ((r = pthread_mutex_trylock(m)) == EBUSY)
            nanosleep(&ms, NULL);
    } else if (way == NL_TIMEDLOCK || way == NL_CLOCKLOCK) {
        do {
            clockid_t clock = way == NL_TIMEDLOCK ? CLOCK_REALTIME : CLOCK_MONOTONIC;
            struct timespec until = in_ms(clock, 200);
            r = way == NL_TIMEDLOCK ? pthread_mutex_timedlock(m, &until)
                                    : pthread_mutex_clocklock(m, clock, &until);
        } while (r == ETIMEDOUT);
    } else {
        r = pthread_mutex_lock(m);
        if (r == 0 || r == EOWNERDEAD) {
            repaired = r == EOWNERDEAD;
            if (repaired)
                pthread_mutex_consistent(m);
            g_in_cond_wait[kind] = 1;
            if (way == NL_COND_TIMEDWAIT) {
                struct timespec until = in_ms(CLOCK_REALTIME, 20);
                r = pthread_cond_timedwait(&g_cond, m, &until);
            } else {
                struct timespec until = in_ms(CLOCK_MONOTONIC, 20);
                r = pthread_cond_clockwait(&g_cond, m, CLOCK_MONOTONIC, &until);
            }
            g_in_cond_wait[kind] = 0;
            r = r == ETIMEDOUT ? 0 : r;
        }
    }
    if (r == EOWNERDEAD) {
        pthread_mutex_consistent(m);
        repaired = 1;
    } else if (r) {
        return -r;
    }
    pthread_mutex_unlock(m);
    return repaired;
}

/* Take g_locks[kind] while a waiter of nativelock_use_by is inside its
   condvar wait (it set g_in_cond_wait holding the mutex, and clears it only
   once it has the mutex back: so, seen set while this holds it, the waiter's
   next step is the relock), and die holding it.  Tries every 1 ms. */
int nativelock_hold_and_die_in_cond_wait(int kind, int how)
{
    if (bad(kind) || kind == NL_ROBUST)
        return -EINVAL;
    for (;;) {
        pthread_mutex_lock(&g_locks[kind]);
        if (g_in_cond_wait[kind]) {
            if (kind == NL_RECURSIVE)
                pthread_mutex_lock(&g_locks[kind]);
            die(how);
        }
        pthread_mutex_unlock(&g_locks[kind]);
        usleep(1000);
    }
}

/* Take g_rwlock for writing (write true) or reading, and give it back. */
int nativelock_rw_use(int write)
{
    int r = write ? pthread_rwlock_wrlock(&g_rwlock) : pthread_rwlock_rdlock(&g_rwlock);
    return r ? -r : -pthread_rwlock_unlock(&g_rwlock);
}

int nativelock_rw_hold_and_die(int how) /* write-lock it and die */
{
    pthread_rwlock_wrlock(&g_rwlock);
    die(how);
}

int nativelock_rw_read_and_die(int how) /* read-lock it and die */
{
    pthread_rwlock_rdlock(&g_rwlock);
    die(how);
}

int nativelock_rw_hold(void)
{
    return -pthread_rwlock_wrlock(&g_rwlock);
}

int nativelock_rw_release(void)
{
    return -pthread_rwlock_unlock(&g_rwlock);
}

long nativelock_rw_address(void)
{
    return (long)&g_rwlock;
}
