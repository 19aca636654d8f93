/* probes.h - what probes.c offers: what assumptions.py discovers and checks the layout with */
#ifndef CLONEGUARD_PROBES_H
#define CLONEGUARD_PROBES_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
uintptr_t cg_thread_pointer(void);
uintptr_t cg_robust_list_head(void);
long cg_gettid(void);
void *cg_lookup(const char *name, const char *version);
long cg_mutex_futex_offset(void);
int cg_probe_clone3(void);
int cg_probe_condwait(long cleanup_off, struct cg_condwait_probe *out);
int cg_probe_mutexwait(struct cg_mutexwait_probe *out);
int cg_probe_timedwait(struct cg_timedwait_probe *out);
int cg_allocator(char *buf, size_t len);
int cg_jemalloc_thread_tcache(void);
int cg_jemalloc_thread_arena(void);
/* cdef: end */

mallctl_fn find_mallctl(void);

#endif
