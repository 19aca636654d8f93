/*
 * guard_internal.h - what the allocator guard's two files share: allocguard.c
 * (malloc) and pyalloc.c (CPython's object allocator).  Hidden: nothing here
 * is visible outside the guard's shared library.
 */
#ifndef CLONEGUARD_GUARD_INTERNAL_H
#define CLONEGUARD_GUARD_INTERNAL_H

#define HIDDEN __attribute__((visibility("hidden")))

/* allocguard.c: the calling task's slot (0: the container, or before the
   guard is active), and whether it is a node process's main task whose
   allocator calls are bracketed by a TLS word rather than its slot's
   counter. */
HIDDEN int cga_caller_slot(void);
HIDDEN int cga_caller_bound(void);

/* pyalloc.c: slot s's process is gone (tcb: its main task's thread
   pointer); 1 if it died inside CPython's object allocator (its pools are
   abandoned, a new generation starts), else 0. */
HIDDEN int py_slot_retire(int s, char *tcb);

#endif
