/* child.h - what child.c offers: how a child is born and runs */
#ifndef CLONEGUARD_CHILD_H
#define CLONEGUARD_CHILD_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
int cg_self_stop_requested(void);
int cg_self_wait_go(void);
/* cdef: end */

long child_clone(struct cg_child *c);                    /* on the monitor thread: pid or -errno */
void child_gate_post(struct cg_child *c, unsigned stop); /* async-signal-safe */

#endif
