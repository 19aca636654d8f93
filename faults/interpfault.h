/* interpfault.h - die half-way through changing interpreter state
 * (interpfault.c).  Mirrored by _build_interpfault.py's cdef. */
#ifndef CLONEGUARD_INTERPFAULT_H
#define CLONEGUARD_INTERPFAULT_H

int interpfault_die_mid_gc_untrack(int stores);
int interpfault_die_mid_gc_track(int stores);
int interpfault_die_mid_list_append(void *list);
int interpfault_die_with_torn_locals(void);
int interpfault_die_inside(const char *library, int period_us, long max_ticks);

#endif
