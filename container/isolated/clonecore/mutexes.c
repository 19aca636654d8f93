/*
 * mutexes.c - native mutexes a dead node process held: found through the
 * tasks blocked on them, proven, released (the monitor's "lock doctor").
 *
 * glibc's plain mutexes (PTHREAD_MUTEX_{NORMAL,RECURSIVE,ERRORCHECK,
 * ADAPTIVE}_NP: std::mutex and std::recursive_mutex, rcl's, Fast DDS's, a C
 * extension's) record their owner's TID in the mutex (__data.__owner).  A
 * node process that dies holding one leaves it locked for good: the kernel
 * recovers robust mutexes only.  The monitor, on its own thread, without the
 * GIL:
 *
 *   sees     each live child's tasks (/proc/<pid>/task) at its birth and
 *            every SEEN_EVERY_NS (AFTER_DEATH_EVERY_NS for a while after a
 *            death), each with where the kernel's pid cursor stood then;
 *   buries   at a death, what it saw of the dead child becomes a dead set;
 *   scans    while a dead set holds a task: every task of the container and
 *            of the live children, by /proc/<tid>/syscall.  A task is blocked
 *            on a plain mutex when it is in futex(uaddr, FUTEX_WAIT, 2) at
 *            the pc of glibc's __lll_lock_wait with, on its stack, a return
 *            address into pthread_mutex_lock or into the relock after
 *            pthread_cond_wait or pthread_cond_timedwait/_clockwait (pc,
 *            stack slot and return addresses are probed at start-up:
 *            probes.c, assumptions.py); or in futex(uaddr, FUTEX_WAIT_BITSET,
 *            2) at the pc of glibc's __futex_abstimed_wait64 returning into
 *            pthread_mutex_timedlock/_clocklock (one function of glibc's:
 *            its waits time out and are retried by the caller, so each try
 *            is caught while it waits); the mutex is at uaddr (__data.__lock
 *            is its first word).  At that same pc, returning into one of the
 *            pthread_rwlock lock calls, it is blocked on a rwlock a writer
 *            or readers hold, whose futex word (probed: __writers_futex for
 *            a writer on a writer, __wrphase_futex for a reader on a writer
 *            or a writer on readers) is uaddr;
 *   proves   its owner O was a task of a dead child: O was seen in it (a
 *            dead child's tasks are all gone, but for its main task, a
 *            zombie until Python reaps it), and the pid cursor has not come
 *            round to O since (Linux hands pids out in cyclic order, so O
 *            was not given to another task meanwhile);
 *   sweeps   HELD_AFTER_NS after a death, the container's memory for plain
 *            mutexes a dead set's task still holds with no task blocked
 *            on them (a waiter that polls with pthread_mutex_trylock never
 *            blocks): heldscan.c, in steps between the monitor's events;
 *            each found is proven and released as below, reported with no
 *            waiter (tid 0);
 *   releases it as its owner's last unlock would: __owner to 0 (only if it
 *            still is O), a recursive count to 0, __nusers one less, the
 *            lock word to 0, one waiter woken; reported CG_MUTEX_RELEASED.
 *            A rwlock records its writer (__data.__cur_writer, written once
 *            it holds the lock, cleared first thing in its unlock) and no
 *            reader: one whose writer W is proven dead is released by
 *            glibc's own writer unlock, run here in W's name (below).
 *
 * Never touched, reported instead (once per waiter and lock):
 *   UNPROVEN  the owner is gone but was not seen in a dead child (a thread
 *             born after the last look, or one that exited holding it);
 *   NO_OWNER  held with no owner written (its owner died between taking the
 *             lock word and writing __owner, or between clearing __owner and
 *             releasing), still so after STUCK_NS;
 *   EXCLUDED  a dead owner's robust, PI, priority-protect, process-shared or
 *             elided mutex (robust ones the kernel recovers itself: each
 *             child has its robust list);
 *   LIBC_LOCK a wait of STUCK_NS on one of glibc's internal locks (malloc
 *             arenas, stdio, the loader: __lll_lock_wait_private; they record
 *             no owner), while a death is recent.
 * For a rwlock (cg_event.code CG_RWLOCK_KIND): UNPROVEN as for a mutex;
 * EXCLUDED a process-shared one (or one not write-locked while a writer is
 * recorded); NO_OWNER a wait of STUCK_NS while no writer is recorded (held
 * by readers, which glibc does not record: a dead reader cannot be told
 * from a live one), while a death is recent.
 * A live owner's mutex is never touched nor reported.  Condition variables'
 * internal locks are not looked at here (gilrepair.c mends the GIL's).
 *
 * Everything runs on the monitor thread: no malloc, no stdio, no lock a dead
 * task could hold (no dladdr: it takes the loader's lock); memory is read
 * with process_vm_readv, so a wrong address is an error, not a fault.
 */
#include "core.h"
#include "mutexes.h"
#include "clonecore.h"
#include "heldscan.h"
#include "monitor.h"
#include "sigsafe.h"

#include <errno.h>
#include <fcntl.h>
#include <linux/futex.h>
#include <pthread.h>
#include <signal.h>
#include <string.h>
#include <sys/syscall.h>
#include <sys/uio.h>
#include <unistd.h>

#define SEEN_EVERY_NS (500 * 1000000LL)
#define AFTER_DEATH_NS (1000 * 1000000LL) /* for this long after a death, */
/* look this often: its siblings block on what it held soon */
#define AFTER_DEATH_EVERY_NS (50 * 1000000LL)
/* the first look, this long after the death: not on the CPU the death's
   report needs (a look reads /proc for every task; on 2 cores it held the
   core's listener off ~0.3 ms) */
#define FIRST_LOOK_NS (2 * 1000000LL)
#define STUCK_NS (1000 * 1000000LL)
/* this long after a death, sweep memory for mutexes its tasks still hold
   that no task blocks on (heldscan.c) */
#define HELD_AFTER_NS (1000 * 1000000LL)
#define RESERVED_PIDS 300 /* where the pid cursor wraps to (kernel/pid.c) */
#define NDEAD 32          /* dead sets kept; the oldest is dropped first */
#define NREPORTED 128     /* (waiter, lock, verdict) already reported */
#define NPENDING 64       /* waits being timed for NO_OWNER / LIBC_LOCK */

/* The kind bits of __data.__kind a plain mutex may have (pthreadP.h):
   the type (0-3) and PTHREAD_MUTEX_NO_ELISION_NP.  Any other bit (robust
   16, PI 32, priority-protect 64, process-shared 128, elision 256) makes it
   EXCLUDED. */
#define MUTEX_TYPE_MASK 3
#define MUTEX_NO_ELISION 512
#define FUTEX_TID_MASK_ 0x3fffffff

struct dead_set {
    int pid; /* 0: empty */
    uint64_t serial;
    struct cg_seen_tasks seen;
};

static struct dead_set g_dead[NDEAD];
static int g_dead_next;
static int g_pid_max, g_cursor; /* ns_last_pid when last read */
static uint64_t g_advanced;     /* how far the cursor moved since start */
static int64_t g_next_look, g_died_at;
static int g_last_dead_pid;
static uint64_t g_last_dead_serial;
static int g_scans;         /* generation of the current scan */
static int64_t g_sweep_due; /* when the next held-mutex sweep starts, 0: none */
static bool g_sweeping;     /* one is under way */

static struct {
    int tid;
    uintptr_t addr;
    int verdict;
} g_reported[NREPORTED];
static int g_reported_next;
static struct {
    int tid;
    uintptr_t addr;
    int verdict;
    int64_t since;
    int scan;
} g_pending[NPENDING];

/* ---- procfs without malloc or stdio ------------------------------------ */

/* "/proc/<id>/<leaf>"; id 0: "/proc/self/<leaf>".  -1 if it does not fit. */
static int proc_path(char *buf, size_t len, int id, const char *leaf)
{
    struct ss_buf o = {buf, len - 1, 0};
    ss_str(&o, "/proc/");
    if (id == 0)
        ss_str(&o, "self");
    else
        ss_dec(&o, id);
    ss_str(&o, "/");
    ss_str(&o, leaf);
    if (o.n >= o.cap)
        return -1;
    ss_cstr(&o);
    return 0;
}

/* Read a small file whole into buf (NUL-terminated): its length, or -errno. */
static ssize_t read_small(const char *path, char *buf, size_t len)
{
    int fd = open(path, O_RDONLY | O_CLOEXEC);
    if (fd < 0)
        return -errno;
    ssize_t n = read(fd, buf, len - 1);
    int err = errno;
    close(fd);
    if (n < 0)
        return -err;
    buf[n] = '\0';
    return n;
}

/* A decimal or 0x-hex number at *p, skipping blanks; *p moves past it. */
static long parse_num(const char **p)
{
    const char *s = *p;
    while (*s == ' ' || *s == '\n')
        s++;
    int neg = *s == '-';
    s += neg;
    unsigned long v = 0;
    if (s[0] == '0' && s[1] == 'x') {
        for (s += 2;; s++) {
            int d = *s >= '0' && *s <= '9' ? *s - '0' : *s >= 'a' && *s <= 'f' ? *s - 'a' + 10 : -1;
            if (d < 0)
                break;
            v = v * 16 + (unsigned long)d;
        }
    } else {
        for (; *s >= '0' && *s <= '9'; s++)
            v = v * 10 + (unsigned long)(*s - '0');
    }
    *p = s;
    return neg ? -(long)v : (long)v;
}

int task_syscall(int tid, struct task_syscall *out)
{
    char path[64], buf[256];
    out->nr = -2;
    if (proc_path(path, sizeof path, tid, "syscall") < 0)
        return -ENAMETOOLONG;
    ssize_t n = read_small(path, buf, sizeof buf);
    if (n <= 0)
        return n < 0 ? (int)n : -EIO;
    if (buf[0] == 'r') /* "running" */
        return 0;
    const char *p = buf;
    long nr = parse_num(&p);
    if (nr >= 0)
        for (int i = 0; i < 6; i++)
            out->args[i] = (uintptr_t)parse_num(&p);
    out->sp = (uintptr_t)parse_num(&p);
    out->pc = (uintptr_t)parse_num(&p);
    out->nr = nr; /* -1: blocked outside a syscall */
    return 0;
}

/* Each tid listed in /proc/<pid>/task (pid 0: the container's own), to fn. */
static void each_task(int pid, void (*fn)(int tid, void *arg), void *arg)
{
    char path[64];
    if (proc_path(path, sizeof path, pid, "task") < 0)
        return;
    int fd = open(path, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (fd < 0)
        return;
    char buf[4096] __attribute__((aligned(8)));
    long n;
    while ((n = syscall(SYS_getdents64, fd, buf, sizeof buf)) > 0)
        for (long off = 0; off < n;) {
            struct {
                uint64_t ino;
                int64_t off;
                unsigned short reclen;
                unsigned char type;
                char name[];
            } *d = (void *)(buf + off);
            off += d->reclen;
            if (d->name[0] >= '0' && d->name[0] <= '9') {
                const char *s = d->name;
                fn((int)parse_num(&s), arg);
            }
        }
    close(fd);
}

static int read_mem(uintptr_t addr, void *out, size_t len)
{
    struct iovec local = {out, len}, remote = {(void *)addr, len};
    return process_vm_readv(getpid(), &local, 1, &remote, 1, 0) == (ssize_t)len ? 0 : -1;
}

static bool task_exists(int tid)
{
    return kill(tid, 0) == 0 || errno == EPERM;
}

/* ---- the pid cursor ---------------------------------------------------- */

static int read_int(const char *path)
{
    char buf[32];
    const char *p = buf;
    return read_small(path, buf, sizeof buf) > 0 ? (int)parse_num(&p) : -1;
}

/* Move g_advanced on by how far the cursor went since the last read.  A
   wrap counts RESERVED_PIDS too many: never too few.  (More than pid_max
   pids between two reads would be missed: SEEN_EVERY_NS apart that is
   tens of thousands of forks a second.) */
static void cursor_update(void)
{
    int c = read_int("/proc/sys/kernel/ns_last_pid");
    if (c < 0 || g_pid_max <= 0)
        return;
    g_advanced += (uint64_t)((c - g_cursor + g_pid_max) % g_pid_max);
    g_cursor = c;
}

/* Has the cursor come round to tid since s was seen (so tid may be another
   task's now)?  The fewest allocations that hand out tid again, from the
   cursor at s.cursor: straight up to it, or up to pid_max and round from
   RESERVED_PIDS. */
static bool maybe_reused(const struct cg_seen_task *s)
{
    long need = s->tid > s->cursor ? (long)s->tid - s->cursor
                                   : (long)s->tid + g_pid_max - s->cursor - RESERVED_PIDS;
    return need <= 0 || g_advanced - s->advanced >= (uint64_t)need;
}

/* ---- seeing and burying ------------------------------------------------- */

static void see_one(int tid, void *arg)
{
    struct cg_seen_tasks *seen = arg;
    for (int i = 0; i < seen->n; i++)
        if (seen->t[i].tid == tid) {
            seen->t[i].cursor = g_cursor;
            seen->t[i].advanced = g_advanced;
            return;
        }
    if (seen->n == CG_SEEN_TASKS) { /* make room: drop what may be reused */
        int k = 0;
        for (int i = 0; i < seen->n; i++)
            if (!maybe_reused(&seen->t[i]))
                seen->t[k++] = seen->t[i];
        seen->n = k;
        if (k == CG_SEEN_TASKS) {
            seen->overflow = 1;
            return;
        }
    }
    seen->t[seen->n++] = (struct cg_seen_task){tid, g_cursor, g_advanced};
}

/* Look at child c's tasks now (the cursor first: a task listed was alive
   at that cursor or later, never earlier). */
void mutexes_see(struct cg_child *c)
{
    if (!cg_cfg()->mutex_repair)
        return;
    cursor_update();
    each_task(c->pid, see_one, &c->seen);
}

/* Child c is dead (every task of it is gone) and about to be reaped. */
void mutexes_bury(const struct cg_child *c)
{
    if (!cg_cfg()->mutex_repair || c->seen.n == 0)
        return;
    struct dead_set *d = &g_dead[g_dead_next];
    g_dead_next = (g_dead_next + 1) % NDEAD;
    d->pid = c->pid;
    d->serial = c->serial;
    d->seen = c->seen;
    g_last_dead_pid = c->pid;
    g_last_dead_serial = c->serial;
    g_next_look = cg_mono_ns() + FIRST_LOOK_NS; /* look for its waiters soon */
    g_sweep_due = cg_mono_ns() + HELD_AFTER_NS; /* and later for what it holds */
    g_died_at = -1;                             /* and often for a while (mutexes_tick) */
}

/* The dead set that proves tid a dead child's task, or NULL.  A task it
   proves is dead even where kill() still finds it: the child's main task
   (tid = its pid) stays a zombie until Python's cg_release reaps it
   (monitor.c leaves it so), and the Python thread that would may itself be
   what waits, holding the GIL, on the mutex that task held (a CRASHED
   publish on Fast DDS's send lock did).  The pid cannot be another task's
   before that reaping, nor after it until the cursor comes round to it. */
static const struct dead_set *dead_owner(int tid)
{
    for (int i = 0; i < NDEAD; i++)
        for (int k = 0; g_dead[i].pid && k < g_dead[i].seen.n; k++)
            if (g_dead[i].seen.t[k].tid == tid)
                return maybe_reused(&g_dead[i].seen.t[k]) ? NULL : &g_dead[i];
    return NULL;
}

/* Forget dead sets whose every task may have been reused: nothing they
   hold can prove an owner any more.  Whether any is left. */
static bool prune_dead(void)
{
    bool any = false;
    for (int i = 0; i < NDEAD; i++) {
        struct dead_set *d = &g_dead[i];
        int k = 0;
        for (int j = 0; d->pid && j < d->seen.n; j++)
            if (!maybe_reused(&d->seen.t[j]))
                d->seen.t[k++] = d->seen.t[j];
        if (d->pid)
            d->seen.n = k;
        if (d->pid && k == 0)
            d->pid = 0;
        any |= d->pid != 0;
    }
    return any;
}

/* ---- reporting ---------------------------------------------------------- */

static void report(int verdict, const struct dead_set *d, int waiter, int owner, int kind,
                   uintptr_t addr)
{
    if (verdict != CG_MUTEX_RELEASED) {
        for (int i = 0; i < NREPORTED; i++)
            if (g_reported[i].tid == waiter && g_reported[i].addr == addr &&
                g_reported[i].verdict == verdict)
                return;
        g_reported[g_reported_next].tid = waiter;
        g_reported[g_reported_next].addr = addr;
        g_reported[g_reported_next].verdict = verdict;
        g_reported_next = (g_reported_next + 1) % NREPORTED;
    }
    struct cg_event ev = {
        .kind = CG_EV_MUTEX,
        .pid = d ? d->pid : g_last_dead_pid,
        .status = verdict,
        .code = kind,
        .serial = d ? d->serial : g_last_dead_serial,
        .addr = addr,
        .tid = waiter,
        .owner = owner,
    };
    monitor_emit(&ev);
}

/* A wait that only counts once it has lasted STUCK_NS. */
static void report_if_stuck(int verdict, int waiter, int owner, int kind, uintptr_t addr,
                            int64_t now)
{
    int free_slot = -1;
    for (int i = 0; i < NPENDING; i++) {
        if (g_pending[i].tid == waiter && g_pending[i].addr == addr &&
            g_pending[i].verdict == verdict) {
            g_pending[i].scan = g_scans;
            if (now - g_pending[i].since >= STUCK_NS)
                report(verdict, NULL, waiter, owner, kind, addr);
            return;
        }
        if (free_slot < 0 && g_pending[i].tid == 0)
            free_slot = i;
    }
    if (free_slot >= 0) {
        g_pending[free_slot].tid = waiter;
        g_pending[free_slot].addr = addr;
        g_pending[free_slot].verdict = verdict;
        g_pending[free_slot].since = now;
        g_pending[free_slot].scan = g_scans;
    }
}

/* ---- the scan ----------------------------------------------------------- */

static bool mutex_caller(uintptr_t ret)
{
    for (int i = 0; i < CG_MUTEX_CALLERS; i++)
        if (ret && ret == (uintptr_t)cg_tcb_layout()->mutex_ret[i])
            return true;
    return false;
}

/* Release mutex m, whose owner `owner` is proven dead, as that owner's last
   unlock would have (nptl/pthread_mutex_unlock.c); false if it changed
   meanwhile. */
static bool release(pthread_mutex_t *m, int owner)
{
    int expected = owner;
    if (!__atomic_compare_exchange_n(&m->__data.__owner, &expected, 0, false, __ATOMIC_ACQ_REL,
                                     __ATOMIC_RELAXED))
        return false;
    if ((m->__data.__kind & MUTEX_TYPE_MASK) == PTHREAD_MUTEX_RECURSIVE_NP)
        m->__data.__count = 0;
    if (m->__data.__nusers > 0)
        m->__data.__nusers--;
    if (__atomic_exchange_n(&m->__data.__lock, 0, __ATOMIC_RELEASE) > 1)
        syscall(SYS_futex, &m->__data.__lock, FUTEX_WAKE_PRIVATE, 1, NULL, NULL, 0);
    return true;
}

static void mutex_waiter(int waiter, uintptr_t addr, int64_t now)
{
    pthread_mutex_t m;
    if (read_mem(addr, &m, sizeof m) < 0 || m.__data.__lock == 0)
        return;
    int owner = m.__data.__owner, kind = m.__data.__kind;
    if (owner == 0) {
        report_if_stuck(CG_MUTEX_NO_OWNER, waiter, 0, kind, addr, now);
        return;
    }
    const struct dead_set *d = owner > 0 ? dead_owner(owner) : NULL;
    if (owner < 0 || (!d && task_exists(owner)))
        return; /* alive: never touched */
    if (!d)
        report(CG_MUTEX_UNPROVEN, NULL, waiter, owner, kind, addr);
    else if (kind & ~(MUTEX_TYPE_MASK | MUTEX_NO_ELISION))
        report(CG_MUTEX_EXCLUDED, d, waiter, owner, kind, addr);
    else if (release((pthread_mutex_t *)addr, owner))
        report(CG_MUTEX_RELEASED, d, waiter, owner, kind, addr);
}

static bool timed_mutex_caller(uintptr_t ret)
{
    for (int i = 0; i < CG_TIMED_TYPES; i++)
        if (ret && ret == (uintptr_t)cg_tcb_layout()->mutex_timed_ret[i])
            return true;
    return false;
}

/* Which pthread_rwlock lock call ret returns into (cg_layout.rwlock_ret's
   index), -1: none. */
static int rwlock_caller(uintptr_t ret)
{
    for (int i = 0; i < CG_RWLOCK_CALLERS; i++)
        if (ret && ret == (uintptr_t)cg_tcb_layout()->rwlock_ret[i])
            return i;
    return -1;
}

/* Release rwlock rw, write-locked by `writer`, proven dead, by glibc's own
   writer unlock.  pthread_rwlock_unlock unlocks as the writer exactly when
   __cur_writer is the caller's tid (else it unlocks as a reader), so this
   thread first takes the writer's place there, by CAS (false if it changed
   meanwhile).  Safe because only the writer itself writes __cur_writer
   while it holds the lock (readers and waiters never do) and it is dead;
   and glibc's unlock takes no lock and never blocks (atomics on the
   rwlock's words and futex wakes): it hands the lock to a waiting writer or
   to the readers as the writer's own unlock would have.  Checked on a live
   rwlock whose writer ended at start-up (cg_probe_timedwait). */
static bool release_rwlock(pthread_rwlock_t *rw, int writer)
{
    int expected = writer;
    if (!__atomic_compare_exchange_n(&rw->__data.__cur_writer, &expected, (int)syscall(SYS_gettid),
                                     false, __ATOMIC_ACQ_REL, __ATOMIC_RELAXED))
        return false;
    return pthread_rwlock_unlock(rw) == 0;
}

/* __readers: a writer holds it (glibc 2.36's PTHREAD_RWLOCK_WRLOCKED) */
#define RWLOCK_WRLOCKED 2

static void rwlock_waiter(int waiter, uintptr_t addr, int64_t now)
{
    pthread_rwlock_t rw;
    if (read_mem(addr, &rw, sizeof rw) < 0)
        return;
    int writer = rw.__data.__cur_writer;
    if (writer == 0) { /* readers hold it, or none recorded */
        report_if_stuck(CG_MUTEX_NO_OWNER, waiter, 0, CG_RWLOCK_KIND, addr, now);
        return;
    }
    const struct dead_set *d = writer > 0 ? dead_owner(writer) : NULL;
    if (writer < 0 || (!d && task_exists(writer)))
        return; /* alive: never touched */
    if (!d)
        report(CG_MUTEX_UNPROVEN, NULL, waiter, writer, CG_RWLOCK_KIND, addr);
    else if (rw.__data.__shared || !(rw.__data.__readers & RWLOCK_WRLOCKED))
        report(CG_MUTEX_EXCLUDED, d, waiter, writer, CG_RWLOCK_KIND, addr);
    else if (release_rwlock((pthread_rwlock_t *)addr, writer))
        report(CG_MUTEX_RELEASED, d, waiter, writer, CG_RWLOCK_KIND, addr);
}

static void look_at(int tid, void *arg)
{
    const struct cg_layout *L = cg_tcb_layout();
    int64_t now = *(int64_t *)arg;
    struct task_syscall sc;
    if (tid == (int)syscall(SYS_gettid) || task_syscall(tid, &sc) < 0 || sc.nr != SYS_futex)
        return;
    int op = (int)sc.args[1] & FUTEX_CMD_MASK;
    uintptr_t addr = sc.args[0];
    if (op == FUTEX_WAIT && (int)sc.args[2] == 2 && sc.pc == (uintptr_t)L->mutex_wait_pc) {
        uintptr_t ret;
        if (read_mem(sc.sp + 8 * (uintptr_t)L->mutex_ret_slot, &ret, sizeof ret) == 0 &&
            mutex_caller(ret))
            mutex_waiter(tid, addr, now);
    } else if (op == FUTEX_WAIT_BITSET && L->timed_wait_pc &&
               sc.pc == (uintptr_t)L->timed_wait_pc) {
        uintptr_t ret;
        int k;
        if (read_mem(sc.sp + 8 * (uintptr_t)L->timed_ret_slot, &ret, sizeof ret) < 0)
            return;
        if ((int)sc.args[2] == 2 && timed_mutex_caller(ret))
            mutex_waiter(tid, addr, now);
        else if ((k = rwlock_caller(ret)) >= 0)
            rwlock_waiter(tid, addr - (uintptr_t)L->rwlock_futex_off[k], now);
    } else if (op == FUTEX_WAIT && sc.pc == (uintptr_t)L->private_wait_pc) {
        report_if_stuck(CG_MUTEX_LIBC_LOCK, tid, 0, -1, addr, now);
    } else if (op == FUTEX_LOCK_PI || op == FUTEX_LOCK_PI2) {
        unsigned word; /* a PI futex word holds its owner */
        int owner;
        if (read_mem(addr, &word, sizeof word) == 0 && (owner = (int)(word & FUTEX_TID_MASK_))) {
            const struct dead_set *d = dead_owner(owner);
            if (d || !task_exists(owner))
                report(d ? CG_MUTEX_EXCLUDED : CG_MUTEX_UNPROVEN, d, tid, owner, -1, addr);
        }
    }
}

/* ---- mutexes held with no waiter (heldscan.c) --------------------------- */

static bool proven_dead(int tid)
{
    return dead_owner(tid) != NULL;
}

/* The range of the tids the dead sets prove dead; false if none. */
static bool dead_range(struct held_owners *o)
{
    o->min = 0x7fffffff, o->max = 0, o->dead = proven_dead;
    for (int i = 0; i < NDEAD; i++)
        for (int k = 0; g_dead[i].pid && k < g_dead[i].seen.n; k++) {
            int tid = g_dead[i].seen.t[k].tid;
            o->min = tid < o->min ? tid : o->min;
            o->max = tid > o->max ? tid : o->max;
        }
    return o->max > 0;
}

/* A place the sweep found: released, as for a waiter, if it still is a
   plain mutex that dead task holds; reported with no waiter (tid 0). */
static void held_found(uintptr_t addr, int owner, int kind)
{
    pthread_mutex_t m;
    if (read_mem(addr, &m, sizeof m) < 0 || m.__data.__owner != owner || m.__data.__lock == 0)
        return;
    const struct dead_set *d = dead_owner(owner);
    if (d && release((pthread_mutex_t *)addr, owner))
        report(CG_MUTEX_RELEASED, d, 0, owner, kind, addr);
}

/* Start or go on with a sweep when it is time; true while one is under way
   (the monitor comes back at once, between its events). */
static bool sweep(int64_t now)
{
    if (g_sweep_due && now >= g_sweep_due && !g_sweeping) {
        g_sweep_due = 0;
        g_sweeping = held_sweep_start();
    }
    struct held_owners owners;
    if (g_sweeping)
        g_sweeping = dead_range(&owners) && held_sweep_step(&owners, held_found);
    return g_sweeping;
}

static void scan(struct cg_child *children, int64_t now)
{
    g_scans++;
    each_task(0, look_at, &now);
    for (struct cg_child *c = children; c; c = c->next)
        each_task(c->pid, look_at, &now);
    for (int i = 0; i < NPENDING; i++) /* waits that ended */
        if (g_pending[i].tid && g_pending[i].scan != g_scans)
            g_pending[i].tid = 0;
}

int mutexes_start(void)
{
    if (!cg_cfg()->mutex_repair)
        return 0;
    g_pid_max = read_int("/proc/sys/kernel/pid_max");
    g_cursor = read_int("/proc/sys/kernel/ns_last_pid");
    return g_pid_max > 0 && g_cursor >= 0 ? 0 : -ENOENT;
}

/* Called by the monitor whenever it wakes: look at the children's tasks,
   and for waiters while a dead set is left, when it is time.  Returns how
   long the monitor may sleep (ms), -1: until something happens. */
int mutexes_tick(struct cg_child *children, int64_t now)
{
    if (!cg_cfg()->mutex_repair)
        return -1;
    bool dead = false;
    if (now >= g_next_look) {
        cursor_update();
        for (struct cg_child *c = children; c; c = c->next)
            each_task(c->pid, see_one, &c->seen);
        dead = prune_dead();
        if (dead)
            scan(children, now);
        if (g_died_at < 0)
            g_died_at = now;
        g_next_look =
            now + (now - g_died_at < AFTER_DEATH_NS ? AFTER_DEATH_EVERY_NS : SEEN_EVERY_NS);
    } else {
        for (int i = 0; i < NDEAD && !dead; i++)
            dead = g_dead[i].pid != 0;
    }
    if (sweep(now))
        return 0;
    if (g_sweep_due && (dead || children))
        return (int)(((g_sweep_due < g_next_look ? g_sweep_due : g_next_look) - now + 999999) /
                     1000000);
    if (!children && !dead)
        return -1;
    return (int)((g_next_look - now + 999999) / 1000000);
}
