/* lastresort.h - what lastresort.c offers: the container watchdog's last resort */
#ifndef CLONEGUARD_LASTRESORT_H
#define CLONEGUARD_LASTRESORT_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
int cg_lastresort_start(int fd, const char *banner);
void cg_lastresort_arm(int64_t after_ns);
void cg_lastresort_stop(void);
/* cdef: end */

#endif
