/* deathtext.h - what deathtext.c offers: the words for a death */
#ifndef CLONEGUARD_DEATHTEXT_H
#define CLONEGUARD_DEATHTEXT_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
const char *cg_repair_name(unsigned bit);
int cg_describe_death(int status, int code, uint32_t repairs, uint32_t alloc, int stop_signal,
                      char *out, int size);
/* cdef: end */

#endif
