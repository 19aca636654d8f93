/* listenerwait.h - what listenerwait.c offers: Fast DDS's participant-listener wait made to sleep
 */
#ifndef CLONEGUARD_LISTENERWAIT_H
#define CLONEGUARD_LISTENERWAIT_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
int cg_bound_listener_wait(char *why_out, int why_size);
long cg_listener_waits_bounded(void);
/* cdef: end */

#endif
