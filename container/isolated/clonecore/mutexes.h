/* mutexes.h - what mutexes.c offers: the lock doctor */
#ifndef CLONEGUARD_MUTEXES_H
#define CLONEGUARD_MUTEXES_H

#include "core.h"

/* All on the monitor thread */
int mutexes_start(void);                                  /* -ENOENT: no pid cursor to read */
void mutexes_see(struct cg_child *c);                     /* look at a child's tasks now */
void mutexes_bury(const struct cg_child *c);              /* c is dead, not yet reaped */
int mutexes_tick(struct cg_child *children, int64_t now); /* sleep ms, -1 */
int task_syscall(int tid, struct task_syscall *out);      /* probes.c too */

#endif
