/* monitor.h - what monitor.c offers: the monitor thread */
#ifndef CLONEGUARD_MONITOR_H
#define CLONEGUARD_MONITOR_H

#include "core.h"

/* Called from Python (the cdef's: scripts/cdef.py). */
/* cdef: begin */
/* 0 if the monitor thread runs real-time (SCHED_FIFO), else the errno that
   refused it; after cg_start */
int cg_monitor_realtime(void);
/* cdef: end */

int monitor_start(int *event_fd);
/* On the monitor thread (or before it runs): have its epoll wait also watch
   fd for input, its events handed over with tag (dumps_event), and stop
   watching it.  0, or -errno. */
int monitor_watch(int fd, void *tag);
void monitor_unwatch(int fd);
int monitor_stop(void);                       /* -EBUSY while a child is unreaped */
int monitor_spawn(struct cg_child *c);        /* from any thread; blocks */
void monitor_wake(void);                      /* async-signal-safe */
void monitor_emit(const struct cg_event *ev); /* on the monitor thread */
void repair_step_aside(struct cg_child *c);   /* on the monitor thread:
                                 c's main task waits for its dump */

#endif
