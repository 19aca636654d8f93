/* nativelock.h - what faults/_build_nativelock.py declares to cffi. */
#ifndef CLONEGUARD_FAULTS_NATIVELOCK_H
#define CLONEGUARD_FAULTS_NATIVELOCK_H

enum { NL_NORMAL, NL_RECURSIVE, NL_ERRORCHECK, NL_ADAPTIVE, NL_ROBUST, NL_KINDS };
enum { NL_SIGKILL, NL_SEGFAULT };
/* How a waiter waits for a mutex (nativelock_use_by). */
enum {
    NL_LOCK,
    NL_TIMEDLOCK,
    NL_CLOCKLOCK,
    NL_COND_TIMEDWAIT,
    NL_COND_CLOCKWAIT,
    NL_TRYLOCK,
    NL_WAYS
};

int nativelock_use(int kind);
int nativelock_hold_and_die(int kind, int how);
int nativelock_hold_and_die_once_waited(int kind, int how);
int nativelock_die_taking(int kind, int how);
int nativelock_hold(int kind);
int nativelock_release(int kind);
int nativelock_thread_exits_holding(int kind);
int nativelock_die_holding_file(int how);
int nativelock_use_file(void);
long nativelock_address(int kind);
int nativelock_use_by(int kind, int way);
int nativelock_hold_and_die_in_cond_wait(int kind, int how);
int nativelock_rw_use(int write);
int nativelock_rw_hold_and_die(int how);
int nativelock_rw_read_and_die(int how);
int nativelock_rw_hold(void);
int nativelock_rw_release(void);
long nativelock_rw_address(void);

#endif
