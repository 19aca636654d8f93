/* herald.h - what herald.c offers: a node's CRASHED event, published without Python */
#ifndef CLONEGUARD_HERALD_H
#define CLONEGUARD_HERALD_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
int cg_herald_start(void *publish, void *write_death, const void *publisher);
int cg_herald_stop(int timeout_ms);
long cg_herald_failures(void);
int cg_herald_arm(struct cg_child *c, void *msg, void *destroy, const char *full_node_name,
                  int pid);
int cg_herald_disarm(struct cg_child *c);
int cg_herald_claimed(const struct cg_child *c);
/* cdef: end */

/* herald_claim on the monitor thread, herald_forget on Python's */
bool herald_claim(struct cg_child *c, int status, int code, bool quarantined);
void herald_forget(struct cg_child *c);

#endif
