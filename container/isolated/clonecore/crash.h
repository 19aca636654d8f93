/* crash.h - what crash.c offers: a child's crash report */
#ifndef CLONEGUARD_CRASH_H
#define CLONEGUARD_CRASH_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
void cg_write_native_stack(void *const *frames, int n, int fd);
int cg_container_crash_report(void);
/* cdef: end */

void crash_report_prepare(void);                 /* in cg_start, never in a handler */
void crash_handlers_install(struct cg_child *c); /* in the child */

#endif
