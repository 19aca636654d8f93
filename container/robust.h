/* robust.h - what robust.c offers (container/_build_robust.py feeds these
   declarations to cffi as its cdef). */
#ifndef CLONEGUARD_ROBUST_H
#define CLONEGUARD_ROBUST_H

#include <pthread.h>
#include <stdint.h>

pthread_mutex_t *rm_new(void);
void rm_free(pthread_mutex_t *m);
int rm_lock(pthread_mutex_t *m, int64_t timeout_ns);
int rm_consistent(pthread_mutex_t *m);
int rm_unlock(pthread_mutex_t *m);

#endif
