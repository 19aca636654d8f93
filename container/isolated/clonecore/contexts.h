/* contexts.h - what contexts.c offers: TLS blocks, and the allocator guard's contexts */
#ifndef CLONEGUARD_CONTEXTS_H
#define CLONEGUARD_CONTEXTS_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
int cg_alloc_slot_stats(int slot, struct cga_slot_stats *out);
int cg_py_slot_stats(int slot, struct cga_py_stats *out);
void cg_child_give_back(struct cg_child *c, long *counts); /* takes the GIL */
int cg_pkeys_in_use(int *keys, int max);                   /* the guard's keys */
int cg_alloc_slot_of(const void *p);
int cg_child_slot(const struct cg_child *c);
int cg_child_set_memory_limit(const struct cg_child *c, uint64_t bytes);
int cg_child_memory(const struct cg_child *c, struct cga_slot_memory *out);
/* cdef: end */

int tls_init(void); /* find glibc's TLS allocator */
char *tls_new(void);
void tls_reset(char *tcb);
void tls_give_back(struct cg_child *c);
int guard_start(void); /* -ENOENT: the guard is not preloaded */
bool guard_active(void);
struct cg_ctx *ctx_take(void);
void guard_bind(struct cg_ctx *x);
void guard_child_start(void);                     /* in the child */
void stop_requests_take(int sig);                 /* in the child: the rig's stop points */
int guard_retire(struct cg_ctx *x, bool faulted); /* CGA_RETIRE_* bits */
/* Child c went over its memory budget (CGA_RETIRE_OVER_BUDGET): its figures
   said at the end of its death text (n: the text's length so far). */
void guard_say_over_budget(struct cg_ctx *x, char *text, size_t cap);
int guard_py_owner(const void *p);   /* slot of a Python block, -1: unknown */
int guard_dump_exclude(int exclude); /* dumps.c, while gdb writes */
/* guard_py_abandon, guard_py_abandoned: repair.h (interp.c uses them) */

#endif
