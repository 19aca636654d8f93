/* clonecore.h - what clonecore.c offers: the calls Python makes, and what cg_start was given */
#ifndef CLONEGUARD_CLONECORE_H
#define CLONEGUARD_CLONECORE_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
int cg_start(const struct cg_layout *layout, const struct cg_config *cfg, int *event_fd);
int cg_stop(void);
int cg_spawn(void *target, uint64_t serial, size_t stack_size, int cgroup_fd, int flags,
             struct cg_child **out);
int cg_request_stop(struct cg_child *c);
int cg_go(struct cg_child *c);
int cg_release(struct cg_child *c);
int cg_abandon(struct cg_child *c, int hold_context);
void *cg_child_tstate(const struct cg_child *c);
/* cdef: end */

/* What cg_start was given (set once, before anything else runs; read-only
   afterwards): the configuration, glibc's TCB layout. */
const struct cg_config *cg_cfg(void);
const struct cg_layout *cg_tcb_layout(void);
/* jemalloc's mallctl when jemalloc is the process's malloc, else NULL. */
mallctl_fn cg_mallctl(void);

#endif
