/* heldscan.h - what heldscan.c offers: mutexes a dead child holds with nobody waiting */
#ifndef CLONEGUARD_HELDSCAN_H
#define CLONEGUARD_HELDSCAN_H

#include "core.h"

/* On the monitor thread, for mutexes.c */
struct held_owners {
    int min, max;          /* every tid dead() may accept is in here */
    bool (*dead)(int tid); /* a task proven dead */
};
bool held_sweep_start(void); /* false: no mapping could be read */
bool held_sweep_step(struct held_owners *owners,
                     void (*found)(uintptr_t addr, int owner, int kind)); /* false: done */

#endif
