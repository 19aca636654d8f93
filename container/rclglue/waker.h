/* waker.h - a container thread that wakes one subscriber node process's
 * executors (waker.c).  Its cdef block is _build_rclglue.py's too. */
#ifndef CLONEGUARD_WAKER_H
#define CLONEGUARD_WAKER_H

#include <stdint.h>

/* cdef: begin */
#define CGW_TOKENS 256 /* guard conditions one waker can wake */

struct cgw_waker;

/* From a container thread: start a waker (its thread belongs to the caller's
   thread group, which must be the container's). 0 or -errno. */
int cgw_new(struct cgw_waker **out);
/* A guard condition (rcl_guard_condition_t *) to wake: its token, or -errno. */
int cgw_add(struct cgw_waker *w, void *guard_condition);
/* After this returns the guard condition is never used again. */
void cgw_remove(struct cgw_waker *w, int token);
/* Ask for one wake-up of token's guard condition: lock-free, from anyone. */
void cgw_post(struct cgw_waker *w, int token);
/* Stop it; its block is kept for reuse, never freed, so late posts stay
   harmless.  0, or -ETIMEDOUT when its thread is stuck (then both are left
   behind). */
int cgw_close(struct cgw_waker *w, int timeout_ms);
/* cdef: end */

#endif
