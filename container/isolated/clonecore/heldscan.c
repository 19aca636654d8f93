/*
 * heldscan.c - plain mutexes a dead node process's task still holds while no
 * task blocks on them, found by sweeping the container's memory (on the
 * monitor thread, for mutexes.c).  A waiter that polls with
 * pthread_mutex_trylock (std::mutex::try_lock in a loop) never blocks, so
 * mutexes.c, which finds a dead owner's mutex through the tasks blocked on
 * it, never sees it: the mutex stays held for good and nobody says so.
 *
 * What a held mutex looks like (glibc 2.36, x86-64: pthread_mutex_t is 40
 * bytes, 8-byte aligned; assumptions.py checks the layout at start-up):
 *   __lock     1 or 2 (held; 2: with waiters)
 *   __count    0, but for a RECURSIVE one: how deep, at least 1
 *   __owner    the holder's tid, a task the caller proves dead
 *   __nusers   at least 1
 *   __kind     a plain private type (NORMAL, RECURSIVE, ERRORCHECK,
 *              ADAPTIVE), with or without NO_ELISION: nothing else
 *   __spins    not negative; __elision 0
 *   __list     zero (only robust mutexes link it)
 * Every 8-byte-aligned place of every private writable mapping
 * (/proc/self/maps) that reads so is handed to the caller, which reads it
 * again, proves its owner dead and releases it as it does for a waiter.
 * Only resident pages are read (mincore): a reservation nobody touched
 * costs nothing.  Memory is read with process_vm_readv, so a mapping that
 * goes meanwhile is an error, not a fault.
 *
 * A sweep is done in steps of at most STEP_BYTES read (and STEP_PAGES
 * looked at), so that the monitor, between two steps, reports deaths as
 * promptly as ever.  No malloc, no stdio: static buffers only.
 */
#include "core.h"
#include "heldscan.h"

#include <errno.h>
#include <fcntl.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/uio.h>
#include <unistd.h>

#define MAX_RANGES 8192
#define STEP_BYTES (8u << 20)  /* resident bytes read per step */
#define STEP_PAGES (64u << 10) /* pages looked at per step (mincore) */
#define PAGE 4096u
#define MUTEX_BYTES 40u
#define MUTEX_PLAIN_KIND (3 | 512) /* the type bits, PTHREAD_MUTEX_NO_ELISION_NP */

static struct {
    uintptr_t lo, hi;
} g_ranges[MAX_RANGES];
static int g_nranges, g_range;                    /* the sweep's ranges; the one it is in */
static uintptr_t g_at;                            /* where in it the next step starts */
static unsigned char g_resident[STEP_PAGES / 16]; /* mincore's answers */
static char g_buf[1u << 20] __attribute__((aligned(8)));
static char g_maps[64u << 10];

static uintptr_t hex(const char **p)
{
    uintptr_t v = 0;
    for (int d; (d = **p >= '0' && **p <= '9'   ? **p - '0'
                     : **p >= 'a' && **p <= 'f' ? **p - 'a' + 10
                                                : -1) >= 0;
         (*p)++)
        v = v * 16 + (uintptr_t)d;
    return v;
}

/* One line of /proc/self/maps: its range, if private and writable, and
   neither this file's buffers (copies of what it read) nor the monitor's
   own stack (mutexes.c reads mutexes into locals there): a copy of a held
   mutex is not one. */
static void take_line(const char *line, uintptr_t sp)
{
    const char *p = line;
    uintptr_t lo = hex(&p);
    if (*p++ != '-')
        return;
    uintptr_t hi = hex(&p);
    if (*p++ != ' ' || p[0] != 'r' || p[1] != 'w' || p[3] != 'p' || g_nranges == MAX_RANGES)
        return;
    if (strstr(p, "[vvar]") || strstr(p, "[vsyscall]"))
        return;
    if ((uintptr_t)g_buf - lo < hi - lo || sp - lo < hi - lo)
        return;
    g_ranges[g_nranges].lo = lo;
    g_ranges[g_nranges].hi = hi;
    g_nranges++;
}

/* A new sweep over the mappings there are now; false if none were read. */
bool held_sweep_start(void)
{
    g_nranges = g_range = 0;
    char here;
    uintptr_t sp = (uintptr_t)&here;
    int fd = open("/proc/self/maps", O_RDONLY | O_CLOEXEC);
    if (fd < 0)
        return false;
    size_t kept = 0; /* a line cut at the buffer's end, moved up */
    ssize_t n;
    while ((n = read(fd, g_maps + kept, sizeof g_maps - 1 - kept)) > 0) {
        size_t len = kept + (size_t)n, start = 0;
        g_maps[len] = '\0';
        for (size_t i = 0; i < len; i++)
            if (g_maps[i] == '\n') {
                g_maps[i] = '\0';
                take_line(g_maps + start, sp);
                start = i + 1;
            }
        kept = len - start;
        memmove(g_maps, g_maps + start, kept);
        if (kept == sizeof g_maps - 1)
            kept = 0; /* no line is that long: drop it */
    }
    close(fd);
    g_at = g_nranges ? g_ranges[0].lo : 0;
    return g_nranges > 0;
}

/* The places in buf (read from addr) that look like a held plain mutex. */
static void look(const char *buf, size_t len, uintptr_t addr, struct held_owners *owners,
                 void (*found)(uintptr_t addr, int owner, int kind))
{
    for (size_t off = 0; off + MUTEX_BYTES <= len; off += 8) {
        const pthread_mutex_t *m = (const pthread_mutex_t *)(const void *)(buf + off);
        int owner = m->__data.__owner;
        if (owner < owners->min || owner > owners->max)
            continue;
        int lock = m->__data.__lock, kind = m->__data.__kind;
        if ((lock != 1 && lock != 2) || m->__data.__nusers == 0 || (kind & ~MUTEX_PLAIN_KIND) ||
            m->__data.__spins < 0 || m->__data.__elision != 0 || m->__data.__list.__prev ||
            m->__data.__list.__next)
            continue;
        if ((kind & 3) == PTHREAD_MUTEX_RECURSIVE_NP ? m->__data.__count == 0
                                                     : m->__data.__count != 0)
            continue;
        if (owners->dead(owner))
            found(addr + off, owner, kind);
    }
}

/* Read [lo, hi) (resident) piece by piece, each overlapping the last by a
   mutex's size, so that none is cut in two; how many bytes were read. */
static size_t read_run(uintptr_t lo, uintptr_t hi, struct held_owners *owners,
                       void (*found)(uintptr_t addr, int owner, int kind))
{
    size_t total = 0;
    while (lo < hi) {
        size_t len = hi - lo < sizeof g_buf ? hi - lo : sizeof g_buf;
        struct iovec local = {g_buf, len}, remote = {(void *)lo, len};
        ssize_t got = process_vm_readv(getpid(), &local, 1, &remote, 1, 0);
        if (got <= 0)
            return total; /* unmapped meanwhile */
        look(g_buf, (size_t)got, lo, owners, found);
        total += (size_t)got;
        if (lo + (size_t)got >= hi || (size_t)got <= MUTEX_BYTES)
            break;
        lo += (size_t)got - MUTEX_BYTES;
    }
    return total;
}

/* The next step of the sweep; false once it has been everywhere. */
bool held_sweep_step(struct held_owners *owners, void (*found)(uintptr_t addr, int owner, int kind))
{
    size_t bytes = 0, pages = 0;
    while (g_range < g_nranges && bytes < STEP_BYTES && pages < STEP_PAGES) {
        uintptr_t hi = g_ranges[g_range].hi;
        if (g_at >= hi) {
            if (++g_range < g_nranges)
                g_at = g_ranges[g_range].lo;
            continue;
        }
        size_t n = (hi - g_at) / PAGE;
        if (n > sizeof g_resident)
            n = sizeof g_resident;
        if (mincore((void *)g_at, n * PAGE, g_resident) < 0) {
            g_at = hi; /* gone meanwhile */
            continue;
        }
        for (size_t i = 0; i < n;) {
            size_t j = i;
            while (j < n && (g_resident[j] & 1))
                j++;
            if (j > i)
                bytes += read_run(g_at + i * PAGE, g_at + j * PAGE, owners, found);
            i = j + 1;
        }
        pages += n;
        g_at += n * PAGE;
    }
    return g_range < g_nranges;
}
