/* robust.c - robust mutexes in container memory (container/robust.py).
 *
 * PTHREAD_MUTEX_ROBUST + ERRORCHECK: a locker is told EOWNERDEAD when the
 * owner died holding it (the kernel walks each dying task's robust list;
 * isolated children register theirs, clonecore.c), and an owner relocking
 * gets EDEADLK instead of hanging.  Its own small extension, so that
 * thread mode (intra-process queues, the bus, the loan pool) needs no clone
 * core. */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <time.h>

#include "robust.h"

pthread_mutex_t *rm_new(void)
{
    pthread_mutex_t *m = calloc(1, sizeof *m);
    pthread_mutexattr_t a;
    if (!m)
        return NULL;
    pthread_mutexattr_init(&a);
    pthread_mutexattr_setrobust(&a, PTHREAD_MUTEX_ROBUST);
    /* ERRORCHECK: relocking by the owner gives EDEADLK, not a hang. */
    pthread_mutexattr_settype(&a, PTHREAD_MUTEX_ERRORCHECK);
    int r = pthread_mutex_init(m, &a);
    pthread_mutexattr_destroy(&a);
    if (r) {
        free(m);
        return NULL;
    }
    return m;
}

void rm_free(pthread_mutex_t *m)
{
    pthread_mutex_destroy(m);
    free(m);
}

/* 0, EOWNERDEAD (we own it, state suspect), ETIMEDOUT, ENOTRECOVERABLE,
   EDEADLK.  timeout_ns < 0: wait forever. */
int rm_lock(pthread_mutex_t *m, int64_t timeout_ns)
{
    if (timeout_ns < 0)
        return pthread_mutex_lock(m);
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    int64_t ns = ts.tv_nsec + timeout_ns % 1000000000;
    ts.tv_sec += timeout_ns / 1000000000 + ns / 1000000000;
    ts.tv_nsec = ns % 1000000000;
    return pthread_mutex_clocklock(m, CLOCK_MONOTONIC, &ts);
}

int rm_consistent(pthread_mutex_t *m)
{
    return pthread_mutex_consistent(m);
}
int rm_unlock(pthread_mutex_t *m)
{
    return pthread_mutex_unlock(m);
}
