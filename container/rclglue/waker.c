/* waker.c - wake an intra-process subscriber's executor without making the
 * publisher take the subscriber's locks.
 *
 * A subscriber's executor sleeps in rcl_wait; what wakes it is its guard
 * condition, and triggering that (rcl -> rmw -> Fast DDS) locks the mutex of
 * every wait set the guard condition is attached to: the *subscriber's*
 * wait-set mutex, a plain std::mutex.  A publisher (another node process)
 * SIGKILLed inside that trigger leaves it locked, and the subscriber never
 * gets out of rcl_wait again (seen: 2 in 30 loaned-payload kills).
 *
 * So a publisher does not trigger; it posts.  Each subscriber node process
 * gets a waker: a container thread (it can die only with the container)
 * that triggers that process's guard conditions.  A post is a bit set in
 * the waker's pending mask and a bump of its futex word, then FUTEX_WAKE:
 * no lock, nothing a poster killed half-way can leave held.  A poster killed
 * between the bit and the bump delays that wake-up until the waker's next
 * periodic scan (WAKER_RESCAN_MS).  The subscriber dying inside rcl_wait
 * holding its own wait-set mutex can block its own waker, which serves
 * nobody else.
 *
 * The table of guard conditions is guarded by a robust mutex, taken by the
 * waker while it triggers and by whoever adds or removes an entry (the
 * subscriber's process, or the container): once cgw_remove returns, the
 * guard condition is never touched again and may be destroyed.
 *
 * A waker's block is never freed.  Publishers find a subscription (and so
 * its waker) through lock-free reads of the bus, so one may still post
 * after the subscriber is gone and its waker closed; that post must land in
 * memory that is still a waker.  Closed blocks go on a free list and are
 * reused by the next cgw_new: a late post there sets a pending bit that at
 * worst wakes some live subscription once (a spurious wake-up, which every
 * executor tolerates).
 */
#include "waker.h"

#include <errno.h>
#include <limits.h>
#include <linux/futex.h>
#include <pthread.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include "rcl/error_handling.h"
#include "rcl/guard_condition.h"

#define WAKER_RESCAN_MS 50

struct cgw_waker {
    _Atomic uint32_t seq;                      /* futex word: bumped by posts */
    _Atomic uint64_t pending[CGW_TOKENS / 64]; /* tokens posted, not yet triggered */
    _Atomic int stop;
    _Atomic int finished;
    pthread_mutex_t lock; /* robust; guards gc[] */
    rcl_guard_condition_t *gc[CGW_TOKENS];
    pthread_t thread;
    struct cgw_waker *next_free; /* on the free list once closed */
};

/* Closed wakers, for reuse; only container threads open and close wakers. */
static pthread_mutex_t free_lock = PTHREAD_MUTEX_INITIALIZER;
static struct cgw_waker *free_list;

static struct cgw_waker *take_block(void)
{
    pthread_mutex_lock(&free_lock);
    struct cgw_waker *w = free_list;
    if (w)
        free_list = w->next_free;
    pthread_mutex_unlock(&free_lock);
    if (!w)
        return calloc(1, sizeof *w);
    /* Late posts may still bump seq or set pending bits: both stay atomic
       and harmless, so only the table and the flags are reset. */
    memset(w->gc, 0, sizeof w->gc);
    atomic_store(&w->stop, 0);
    atomic_store(&w->finished, 0);
    w->next_free = NULL;
    return w;
}

static void put_block(struct cgw_waker *w)
{
    pthread_mutex_lock(&free_lock);
    w->next_free = free_list;
    free_list = w;
    pthread_mutex_unlock(&free_lock);
}

static int lock_table(struct cgw_waker *w)
{
    int r = pthread_mutex_lock(&w->lock);
    if (r == EOWNERDEAD) {
        /* Its owner died adding or removing an entry: each is one store. */
        pthread_mutex_consistent(&w->lock);
        r = 0;
    }
    return r;
}

static void trigger_pending(struct cgw_waker *w)
{
    for (int word = 0; word < CGW_TOKENS / 64; word++) {
        uint64_t bits = atomic_exchange(&w->pending[word], 0);
        while (bits) {
            int token = word * 64 + __builtin_ctzll(bits);
            bits &= bits - 1;
            if (lock_table(w) != 0)
                continue;
            rcl_guard_condition_t *gc = w->gc[token];
            if (gc && rcl_trigger_guard_condition(gc) != RCL_RET_OK)
                rcl_reset_error(); /* destroyed under us: nothing to wake */
            pthread_mutex_unlock(&w->lock);
        }
    }
}

static void *waker_main(void *arg)
{
    struct cgw_waker *w = arg;
    struct timespec rescan = {0, WAKER_RESCAN_MS * 1000000L};
    while (!atomic_load(&w->stop)) {
        uint32_t seen = atomic_load(&w->seq);
        trigger_pending(w);
        syscall(SYS_futex, &w->seq, FUTEX_WAIT_PRIVATE, seen, &rescan, NULL, 0);
    }
    atomic_store(&w->finished, 1);
    return NULL;
}

int cgw_new(struct cgw_waker **out)
{
    struct cgw_waker *w = take_block();
    if (!w)
        return -ENOMEM;
    pthread_mutexattr_t a;
    pthread_mutexattr_init(&a);
    pthread_mutexattr_setrobust(&a, PTHREAD_MUTEX_ROBUST);
    pthread_mutex_init(&w->lock, &a);
    pthread_mutexattr_destroy(&a);
    /* Signals stay with the threads that handle them. */
    sigset_t all, old;
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    int r = pthread_create(&w->thread, NULL, waker_main, w);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (r) {
        pthread_mutex_destroy(&w->lock);
        put_block(w);
        return -r;
    }
    *out = w;
    return 0;
}

int cgw_add(struct cgw_waker *w, void *guard_condition)
{
    if (lock_table(w) != 0)
        return -EDEADLK;
    int token = -ENOSPC;
    for (int i = 0; i < CGW_TOKENS; i++)
        if (!w->gc[i]) {
            w->gc[i] = guard_condition;
            token = i;
            break;
        }
    pthread_mutex_unlock(&w->lock);
    return token;
}

void cgw_remove(struct cgw_waker *w, int token)
{
    if (token < 0 || token >= CGW_TOKENS || lock_table(w) != 0)
        return;
    w->gc[token] = NULL;
    pthread_mutex_unlock(&w->lock);
}

void cgw_post(struct cgw_waker *w, int token)
{
    if (token < 0 || token >= CGW_TOKENS)
        return;
    atomic_fetch_or(&w->pending[token / 64], (uint64_t)1 << (token % 64));
    atomic_fetch_add(&w->seq, 1);
    syscall(SYS_futex, &w->seq, FUTEX_WAKE_PRIVATE, 1, NULL, NULL, 0);
}

int cgw_close(struct cgw_waker *w, int timeout_ms)
{
    atomic_store(&w->stop, 1);
    atomic_fetch_add(&w->seq, 1);
    syscall(SYS_futex, &w->seq, FUTEX_WAKE_PRIVATE, INT_MAX, NULL, NULL, 0);
    for (int waited = 0; !atomic_load(&w->finished); waited++) {
        if (waited >= timeout_ms) {
            /* Stuck in its (dead) subscriber's wait-set mutex: it and this
               block are left behind, never to be touched by anyone. */
            pthread_detach(w->thread);
            return -ETIMEDOUT;
        }
        usleep(1000);
    }
    pthread_join(w->thread, NULL);
    pthread_mutex_destroy(&w->lock);
    put_block(w);
    return 0;
}
