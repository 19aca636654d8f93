/* pkeys.h - what pkeys.c offers: memory protection keys, and the facts per-node heap protection
 * rests on */
#ifndef CLONEGUARD_PKEYS_H
#define CLONEGUARD_PKEYS_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
struct cg_pkeys_probe {
    int cpu_pku, os_pke; /* CPUID.7.0:ECX bits 3 and 4 */
    int keys;            /* pkey_alloc gave this many (all freed) */
    int alloc_errno;     /* why the last pkey_alloc failed, 0: none did */
    uint32_t pkru;       /* the calling thread's PKRU (os_pke only) */
    int mprotect_keeps;  /* 1 yes, 0 no, -1 not probed */
    int thread_inherits; /* 1 yes, 0 no, -1 not probed */
    int write_faults;    /* 1 yes, 0 no, -1 not probed */
};
int cg_pkeys_probe(struct cg_pkeys_probe *out);
/* cdef: end */

#endif
