/* dumps.h - what dumps.c offers: --core-dumps, and the watch clock */
#ifndef CLONEGUARD_DUMPS_H
#define CLONEGUARD_DUMPS_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
int64_t cg_watch_clock_ns(void); /* any thread: CLOCK_MONOTONIC less dumps' time */
/* cdef: end */

/* On the monitor thread, but dumps_ask */
int dumps_start(void);                     /* with cg_config.core_dumps only */
bool dumps_ask(struct cg_child *c);        /* a crashing child; async-signal-safe */
bool dumps_event(void *tag, int64_t now);  /* true: an epoll tag of dumps.c's */
int dumps_tick(int64_t now, int sleep_ms); /* sleep ms, -1 */
void dumps_forget(struct cg_child *c);     /* c is dead, about to be reported */
void dumps_stop(void);

#endif
