/* gilfault.h - where gilfault_die_in_gil() dies (gilfault.c).  Mirrored by
 * _build_gilfault.py's cdef. */
#ifndef CLONEGUARD_GILFAULT_H
#define CLONEGUARD_GILFAULT_H

enum {
    GILFAULT_DROP_GIL_LOCKED = 1,
    GILFAULT_TAKE_GIL_HANDOVER = 2,
    GILFAULT_TAKE_GIL_CHECKING = 3,
    GILFAULT_SWITCH_MUTEX = 4,
    GILFAULT_DROP_GIL_SIGNALLING = 5,
};

int gilfault_die_in_gil(int where);

#endif
