/* memwatch.h - what memwatch.c offers: the container's memory watch */
#ifndef CLONEGUARD_MEMWATCH_H
#define CLONEGUARD_MEMWATCH_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
int cg_memwatch_set(int usage_fd, int stat_fd, const char *stat_key, int meminfo, uint64_t limit,
                    uint64_t margin); /* before cg_start */
int cg_child_set_oom_score_adj(struct cg_child *c, int adj);
/* cdef: end */

/* On the monitor thread */
int memwatch_tick(struct cg_child *children, int sleep_ms); /* sleep ms */
void memwatch_say(const struct cg_child *c, char *text, size_t cap);

#endif
