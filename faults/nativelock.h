/* nativelock.h - what faults/_build_nativelock.py declares to cffi. */
#ifndef CLONEGUARD_FAULTS_NATIVELOCK_H
#define CLONEGUARD_FAULTS_NATIVELOCK_H

enum { NL_NORMAL, NL_RECURSIVE, NL_ERRORCHECK, NL_ADAPTIVE, NL_ROBUST, NL_KINDS };
enum { NL_SIGKILL, NL_SEGFAULT };

int nativelock_use(int kind);
int nativelock_hold_and_die(int kind, int how);
int nativelock_die_taking(int kind, int how);
int nativelock_hold(int kind);
int nativelock_release(int kind);
int nativelock_thread_exits_holding(int kind);
int nativelock_die_holding_file(int how);
int nativelock_use_file(void);
long nativelock_address(int kind);

#endif
