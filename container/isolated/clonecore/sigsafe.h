/*
 * sigsafe.h - text without malloc, locks or stdio, for code that runs in a
 * signal handler, on a dying task or beside one that may hold any lock:
 * crash reports (crash.c), procfs paths (mutexes.c), a dump's reason
 * (dumps.c), Python stacks (gilrepair.c), the last-resort watchdog
 * (lastresort.c).  A buffer never overflows and a writer never fails: what
 * does not fit is cut.  Only write(2) is called.  No includes of the core's.
 */
#ifndef CLONEGUARD_SIGSAFE_H
#define CLONEGUARD_SIGSAFE_H

#include <stddef.h>
#include <stdint.h>

/* Text built in b: n bytes so far, at most cap (one byte of b beyond cap
   stays for the NUL of ss_cstr). */
struct ss_buf {
    char *b;
    size_t cap, n;
};
#define SS_BUF(array) ((struct ss_buf){(array), sizeof(array) - 1, 0})

void ss_mem(struct ss_buf *o, const char *s, size_t n);
void ss_str(struct ss_buf *o, const char *s); /* NULL: nothing */
void ss_dec(struct ss_buf *o, long v);
void ss_hex(struct ss_buf *o, unsigned long v); /* "0x..." */
/* num / den with `decimals` digits after the point (0 to 3), rounded to the
   nearest, ties to even: what printf's "%.*f" writes of a value it holds
   exactly (a byte count over 1024 or 1 MiB, say). */
void ss_ratio(struct ss_buf *o, uint64_t num, uint64_t den, int decimals);
char *ss_cstr(struct ss_buf *o); /* b, NUL-terminated */
/* All of it to fd, again after EINTR and short writes: 0, or -1. */
int ss_write_all(int fd, const char *s, size_t n);
/* The text so far to fd, then empty again. */
void ss_flush(struct ss_buf *o, int fd);

#endif
