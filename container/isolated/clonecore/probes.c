/*
 * probes.c - small helpers assumptions.py uses to discover and check the
 * layout the core rests on (the thread pointer, the kernel's robust list,
 * glibc symbols, a live condvar waiter's record), and which allocator the
 * process runs on.  Called from Python at start-up, before any child exists.
 */
#include "core.h"
#include "probes.h"
#include "mutexes.h"

#include <asm/prctl.h>
#include <dlfcn.h>
#include <errno.h>
#include <linux/futex.h>
#include <pthread.h>
#include <sched.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <unistd.h>

uintptr_t cg_thread_pointer(void)
{
    unsigned long fs = 0;
    syscall(SYS_arch_prctl, ARCH_GET_FS, &fs);
    return fs;
}

uintptr_t cg_robust_list_head(void) /* what the kernel has for this task */
{
    void *head = NULL;
    size_t len = 0;
    if (syscall(SYS_get_robust_list, 0, &head, &len) != 0)
        return 0;
    return (uintptr_t)head;
}

long cg_gettid(void)
{
    return syscall(SYS_gettid);
}

void *cg_lookup(const char *name, const char *version)
{
    return version ? dlvsym(RTLD_DEFAULT, name, version) : dlsym(RTLD_DEFAULT, name);
}

long cg_mutex_futex_offset(void) /* glibc: futex word minus list.__next */
{
    return (long)offsetof(pthread_mutex_t, __data.__lock) -
           (long)offsetof(pthread_mutex_t, __data.__list.__next);
}

int cg_probe_clone3(void) /* 0 if the kernel has clone3, else errno */
{
    /* A size of 0 is below CLONE_ARGS_SIZE_VER0: EINVAL if clone3 exists. */
    long r = syscall(SYS_clone3, NULL, (size_t)0);
    return (r < 0 && errno == EINVAL) ? 0 : (r < 0 ? errno : EEXIST);
}

struct probe_arg {
    pthread_mutex_t m;
    pthread_cond_t cv;
    int go, ready;
    long cleanup_off;
    char *sp;
    char *volatile tcb;
    void *before, *after; /* its .cleanup before / after the wait */
};

static void *probe_waiter(void *p)
{
    struct probe_arg *a = p;
    char here;
    a->sp = &here;
    pthread_mutex_lock(&a->m);
    a->tcb = (char *)cg_thread_pointer();
    a->before = *(void **)(a->tcb + a->cleanup_off);
    __atomic_store_n(&a->ready, 1, __ATOMIC_RELEASE);
    while (!a->go)
        pthread_cond_wait(&a->cv, &a->m);
    a->after = *(void **)(a->tcb + a->cleanup_off);
    pthread_mutex_unlock(&a->m);
    return NULL;
}

int cg_probe_condwait(long cleanup_off, struct cg_condwait_probe *out)
{
    memset(out, 0, sizeof *out);
    struct probe_arg a;
    memset(&a, 0, sizeof a);
    a.cleanup_off = cleanup_off;
    pthread_mutex_init(&a.m, NULL);
    pthread_cond_init(&a.cv, NULL);
    pthread_t t;
    if (pthread_create(&t, NULL, probe_waiter, &a) != 0)
        return -EAGAIN;
    while (!__atomic_load_n(&a.ready, __ATOMIC_ACQUIRE))
        sched_yield();
    struct _pthread_cleanup_buffer *buf = NULL;
    for (int i = 0; i < 2000 && (!buf || buf == a.before); i++) { /* ~2 s */
        buf = __atomic_load_n((struct _pthread_cleanup_buffer **)(a.tcb + cleanup_off),
                              __ATOMIC_ACQUIRE);
        if (!buf || buf == a.before)
            usleep(1000);
    }
    if (buf == a.before)
        buf = NULL;
    if (buf) {
        out->found = 1;
        char *lo = a.sp - 65536, *hi = a.sp + 65536;
        struct cg_cond_cbuf *cb = buf->__arg;
        out->buf_on_stack =
            (char *)buf > lo && (char *)buf < hi && (char *)cb > lo && (char *)cb < hi;
        if (out->buf_on_stack) {
            out->routine = (uintptr_t)buf->__routine;
            out->cbuf_matches = cb->cond == &a.cv && cb->mutex == &a.m;
            out->wseq_matches = cb->wseq + 2 == a.cv.__data.__wseq.__value64;
            out->holds_ref = a.cv.__data.__g_refs[cb->wseq & 1] == 2;
            Dl_info info;
            out->routine_in_libc = dladdr((void *)out->routine, &info) && info.dli_fname &&
                                   strstr(info.dli_fname, "libc.so");
        }
    }
    pthread_mutex_lock(&a.m);
    a.go = 1;
    pthread_cond_signal(&a.cv);
    pthread_mutex_unlock(&a.m);
    pthread_join(t, NULL);
    out->cleared_after = out->found && a.after == a.before;
    pthread_cond_destroy(&a.cv);
    pthread_mutex_destroy(&a.m);
    return 0;
}

/* "glibc" or "jemalloc <version>": which malloc the process runs on. */
mallctl_fn find_mallctl(void)
{
    mallctl_fn f = (mallctl_fn)dlsym(RTLD_DEFAULT, "mallctl");
    Dl_info a, b;
    /* jemalloc must be the malloc in use, not merely loaded. */
    if (!f || !dladdr((void *)f, &a) || !dladdr(dlsym(RTLD_DEFAULT, "malloc"), &b) ||
        a.dli_fbase != b.dli_fbase)
        return NULL;
    return f;
}

int cg_allocator(char *buf, size_t len)
{
    mallctl_fn f = find_mallctl();
    const char *v = NULL;
    size_t sz = sizeof v;
    if (f && f("version", &v, &sz, NULL, 0) == 0 && v)
        snprintf(buf, len, "jemalloc %s", v);
    else
        snprintf(buf, len, "glibc");
    return f != NULL;
}

/* Read one jemalloc setting of the calling thread into out (size bytes):
   0, or -1 without jemalloc (or without that setting). */
static int read_mallctl(const char *name, void *out, size_t size)
{
    mallctl_fn f = find_mallctl();
    size_t sz = size;
    return f && f(name, out, &sz, NULL, 0) == 0 ? 0 : -1;
}

/* Whether the calling thread has a jemalloc thread cache: 1/0; -1 without
   jemalloc. */
int cg_jemalloc_thread_tcache(void)
{
    bool on;
    return read_mallctl("thread.tcache.enabled", &on, sizeof on) < 0 ? -1 : on;
}

/* The jemalloc arena the calling thread allocates from; -1 without
   jemalloc. */
int cg_jemalloc_thread_arena(void)
{
    unsigned a;
    return read_mallctl("thread.arena", &a, sizeof a) < 0 ? -1 : (int)a;
}

/* ---- Where a task blocked on a mutex waits, seen from outside ---------- */

struct mutex_waiter {
    pthread_mutex_t *m;
    pthread_cond_t *cv;      /* NULL: pthread_mutex_lock; else cond_wait */
    volatile int tid, phase; /* phase 1: about to block, 2: done */
    int *word;               /* __lll_lock_wait_private: the lock word */
};

static void *mutex_waiter_main(void *p)
{
    struct mutex_waiter *w = p;
    w->tid = (int)syscall(SYS_gettid);
    if (w->word) {
        void (*wait_private)(int *) =
            (void (*)(int *))dlvsym(RTLD_DEFAULT, "__lll_lock_wait_private", "GLIBC_PRIVATE");
        __atomic_store_n(&w->phase, 1, __ATOMIC_RELEASE);
        wait_private(w->word); /* returns holding it (word 2) */
    } else if (w->cv) {
        pthread_mutex_lock(w->m);
        __atomic_store_n(&w->phase, 1, __ATOMIC_RELEASE);
        pthread_cond_wait(w->cv, w->m); /* relocks: cond_lock */
        pthread_mutex_unlock(w->m);
    } else {
        __atomic_store_n(&w->phase, 1, __ATOMIC_RELEASE);
        pthread_mutex_lock(w->m);
        pthread_mutex_unlock(w->m);
    }
    __atomic_store_n(&w->phase, 2, __ATOMIC_RELEASE);
    return NULL;
}

/* Wait (~2 s at most) until task tid is in futex() on a word in
   [lo, lo + len); its view. */
static int wait_in_futex_within(int tid, const void *lo, size_t len, struct task_syscall *sc)
{
    for (int i = 0; i < 2000; i++) {
        if (task_syscall(tid, sc) == 0 && sc->nr == SYS_futex && sc->args[0] - (uintptr_t)lo < len)
            return 0;
        usleep(1000);
    }
    return -ETIMEDOUT;
}

static int wait_in_futex(int tid, const void *uaddr, struct task_syscall *sc)
{
    return wait_in_futex_within(tid, uaddr, 1, sc);
}

static uintptr_t stack_word(uintptr_t sp, int i)
{
    return ((uintptr_t *)sp)[i];
}

/* Block a pthread on a mutex of each kind glibc waits for in __lll_lock_wait
   (PTHREAD_MUTEX_{NORMAL,RECURSIVE,ERRORCHECK,ADAPTIVE}_NP, k = 0..3, and the
   relock of each after pthread_cond_wait, k = 4..7: __pthread_mutex_cond_lock
   returns from a place of its own for each type), and on a glibc-internal lock
   (__lll_lock_wait_private), and read where each waits, from outside, the
   way mutexes.c will: /proc/<tid>/syscall gives the futex call, its pc and
   sp, and the waiter's stack, above sp, the return address into its caller.
   What the mutexes were and the probes saw is checked by assumptions.py. */
int cg_probe_mutexwait(struct cg_mutexwait_probe *out)
{
    memset(out, 0, sizeof *out);
    void *libc = dlopen("libc.so.6", RTLD_NOW | RTLD_NOLOAD);
    void *lock_fn = libc ? dlsym(libc, "pthread_mutex_lock") : NULL;
    if (libc)
        dlclose(libc);
    if (!lock_fn || !dlvsym(RTLD_DEFAULT, "__lll_lock_wait_private", "GLIBC_PRIVATE"))
        return -ENOENT;
    out->self_tid = (int)syscall(SYS_gettid);
    for (int k = 0; k < CG_MUTEX_CALLERS; k++) {
        pthread_mutex_t m;
        pthread_mutexattr_t at;
        pthread_cond_t cv = PTHREAD_COND_INITIALIZER;
        pthread_mutexattr_init(&at);
        bool relock = k >= CG_MUTEX_TYPES;
        pthread_mutexattr_settype(&at, k % CG_MUTEX_TYPES);
        pthread_mutex_init(&m, &at);
        pthread_mutexattr_destroy(&at);
        struct mutex_waiter w = {&m, relock ? &cv : NULL, 0, 0, NULL};
        struct task_syscall sc;
        pthread_t t;
        if (w.cv == NULL)
            pthread_mutex_lock(&m);
        if (pthread_create(&t, NULL, mutex_waiter_main, &w) != 0)
            return -EAGAIN;
        while (__atomic_load_n(&w.phase, __ATOMIC_ACQUIRE) == 0)
            sched_yield();
        if (w.cv) { /* it waits on cv; take m, wake it */
            if (wait_in_futex(w.tid, &cv.__data.__g_signals[0], &sc) < 0)
                wait_in_futex(w.tid, &cv.__data.__g_signals[1], &sc);
            pthread_mutex_lock(&m);
            pthread_cond_signal(&cv);
        }
        int seen = wait_in_futex(w.tid, &m, &sc) == 0;
        out->kind[k] = m.__data.__kind;
        out->owner_is_self[k] = m.__data.__owner == out->self_tid;
        if (seen) {
            out->op[k] = (int)sc.args[1];
            out->val[k] = (int)sc.args[2];
            out->pc[k] = sc.pc;
            /* The return address: the first word above sp that lies in
               pthread_mutex_lock (by dladdr) for a plain lock; for the
               relock, the word at the same place. */
            for (int i = 0; i < 32 && !relock; i++) {
                Dl_info info;
                uintptr_t v = stack_word(sc.sp, i);
                if (dladdr((void *)v, &info) && info.dli_saddr == lock_fn) {
                    out->ret_slot[k] = i;
                    out->ret[k] = v;
                    break;
                }
            }
            if (relock && out->ret[0]) {
                out->ret_slot[k] = out->ret_slot[0];
                out->ret[k] = stack_word(sc.sp, out->ret_slot[0]);
            }
            Dl_info info;
            out->ret_in_libc[k] = out->ret[k] && dladdr((void *)out->ret[k], &info) &&
                                  info.dli_fname && strstr(info.dli_fname, "libc.so");
        }
        out->seen[k] = seen;
        pthread_mutex_unlock(&m);
        pthread_join(t, NULL);
        pthread_mutex_destroy(&m);
        pthread_cond_destroy(&cv);
    }
    /* A glibc-internal lock (no owner recorded): word 2 = held, contended. */
    int word = 2;
    struct mutex_waiter w = {NULL, NULL, 0, 0, &word};
    struct task_syscall sc;
    pthread_t t;
    if (pthread_create(&t, NULL, mutex_waiter_main, &w) != 0)
        return -EAGAIN;
    while (__atomic_load_n(&w.phase, __ATOMIC_ACQUIRE) == 0)
        sched_yield();
    if (wait_in_futex(w.tid, &word, &sc) == 0) {
        out->private_seen = 1;
        out->private_pc = sc.pc;
        out->private_op = (int)sc.args[1];
        out->private_val = (int)sc.args[2];
    }
    __atomic_store_n(&word, 0, __ATOMIC_RELEASE);
    syscall(SYS_futex, &word, FUTEX_WAKE_PRIVATE, 1, NULL, NULL, 0);
    pthread_join(t, NULL);
    return 0;
}

/* ---- Where a task blocked in a timed lock or on a rwlock waits --------- */

/* What a timed waiter calls: the two timed mutex locks, then the rwlock
   calls in the order of cg_layout.rwlock_ret (the last three are the first
   three again, on a rwlock readers hold). */
enum { TW_TIMEDLOCK, TW_CLOCKLOCK, TW_RWLOCK };
static const char *const rwlock_fn[CG_RWLOCK_CALLERS] = {
    "pthread_rwlock_wrlock", "pthread_rwlock_timedwrlock", "pthread_rwlock_clockwrlock",
    "pthread_rwlock_rdlock", "pthread_rwlock_timedrdlock", "pthread_rwlock_clockrdlock",
    "pthread_rwlock_wrlock", "pthread_rwlock_timedwrlock", "pthread_rwlock_clockwrlock",
};

struct timed_waiter {
    pthread_mutex_t *m;
    pthread_rwlock_t *rw;
    int how;                 /* TW_TIMEDLOCK, TW_CLOCKLOCK, TW_RWLOCK + k */
    volatile int tid, phase; /* phase 1: about to block, 2: done */
};

static void *timed_waiter_main(void *p)
{
    struct timed_waiter *w = p;
    /* The ...timed... calls take CLOCK_REALTIME (FUTEX_CLOCK_REALTIME);
       the ...clock... ones are given CLOCK_MONOTONIC. */
    int k = (w->how - TW_RWLOCK) % 6;
    clockid_t clock = w->how == TW_CLOCKLOCK || (w->how >= TW_RWLOCK && k % 3 == 2)
                          ? CLOCK_MONOTONIC
                          : CLOCK_REALTIME;
    struct timespec until;
    clock_gettime(clock, &until);
    until.tv_sec += 10; /* well past the probe's own 2 s waits */
    w->tid = (int)syscall(SYS_gettid);
    __atomic_store_n(&w->phase, 1, __ATOMIC_RELEASE);
    int r;
    switch (w->how < TW_RWLOCK ? w->how : TW_RWLOCK + k) {
    case TW_TIMEDLOCK:
        r = pthread_mutex_timedlock(w->m, &until);
        break;
    case TW_CLOCKLOCK:
        r = pthread_mutex_clocklock(w->m, clock, &until);
        break;
    case TW_RWLOCK + 0:
        r = pthread_rwlock_wrlock(w->rw);
        break;
    case TW_RWLOCK + 1:
        r = pthread_rwlock_timedwrlock(w->rw, &until);
        break;
    case TW_RWLOCK + 2:
        r = pthread_rwlock_clockwrlock(w->rw, clock, &until);
        break;
    case TW_RWLOCK + 3:
        r = pthread_rwlock_rdlock(w->rw);
        break;
    case TW_RWLOCK + 4:
        r = pthread_rwlock_timedrdlock(w->rw, &until);
        break;
    default:
        r = pthread_rwlock_clockrdlock(w->rw, clock, &until);
        break;
    }
    if (r == 0 && w->m)
        pthread_mutex_unlock(w->m);
    else if (r == 0)
        pthread_rwlock_unlock(w->rw);
    __atomic_store_n(&w->phase, 2, __ATOMIC_RELEASE);
    return NULL;
}

static int start_timed_waiter(pthread_t *t, struct timed_waiter *w)
{
    if (pthread_create(t, NULL, timed_waiter_main, w) != 0)
        return -EAGAIN;
    while (__atomic_load_n(&w->phase, __ATOMIC_ACQUIRE) == 0)
        sched_yield();
    return 0;
}

struct rw_writer {
    pthread_rwlock_t *rw;
    int tid;
};

static void *write_lock_and_end(void *p) /* a writer that ends holding it */
{
    struct rw_writer *w = p;
    w->tid = (int)syscall(SYS_gettid);
    pthread_rwlock_wrlock(w->rw);
    return NULL;
}

/* Block a pthread in pthread_mutex_timedlock and in pthread_mutex_clocklock
   on a mutex of each plain type, and in each pthread_rwlock lock call on a
   rwlock a writer holds, and read where each waits from outside, as
   mutexes.c will (see cg_probe_mutexwait).  A rwlock waiter's return
   address is found by dladdr, into the exported rwlock function; a timed
   mutex waiter's is not (pthread_mutex_timedlock and _clocklock jump to a
   function of glibc's own, not exported): it is read at the same stack word,
   since it waits at the same pc (assumptions.py checks that it is, and that
   what is there is an address into libc of its own).  The rwlock's writer is a
   thread that ended holding it; then this thread writes itself into
   __cur_writer and calls pthread_rwlock_unlock, as the monitor releases a
   dead writer's rwlock: the waiter must get it within 2 s.  For the last
   three (writers blocked on readers, who record nothing) this thread holds
   it for reading, and gives it back. */
int cg_probe_timedwait(struct cg_timedwait_probe *out)
{
    memset(out, 0, sizeof *out);
    out->self_tid = (int)syscall(SYS_gettid);
    out->off_wrphase_futex = (long)offsetof(pthread_rwlock_t, __data.__wrphase_futex);
    out->off_writers_futex = (long)offsetof(pthread_rwlock_t, __data.__writers_futex);
    void *libc = dlopen("libc.so.6", RTLD_NOW | RTLD_NOLOAD);
    void *rw_fn[CG_RWLOCK_CALLERS] = {0};
    for (int k = 0; libc && k < CG_RWLOCK_CALLERS; k++)
        rw_fn[k] = dlsym(libc, rwlock_fn[k]);
    Dl_info libc_info;
    int have_libc = libc && dladdr(dlsym(libc, "pthread_mutex_timedlock"), &libc_info);
    if (libc)
        dlclose(libc);
    if (!have_libc)
        return -ENOENT;
    for (int k = 0; k < CG_RWLOCK_CALLERS; k++) {
        /* malloc'd: left behind, waiter and all, if the release fails */
        struct {
            pthread_rwlock_t rw;
            struct timed_waiter w;
        } *b = malloc(sizeof *b);
        if (!b)
            return -ENOMEM;
        pthread_rwlock_t *rw = &b->rw;
        pthread_rwlock_init(rw, NULL);
        struct rw_writer wr = {rw, 0};
        pthread_t t;
        bool readers = k >= 6;
        if (readers) {
            pthread_rwlock_rdlock(rw);
        } else if (pthread_create(&t, NULL, write_lock_and_end, &wr) != 0) {
            free(b);
            return -EAGAIN;
        } else {
            pthread_join(t, NULL);
        }
        out->rw_writer_recorded[k] = readers || (rw->__data.__cur_writer == wr.tid && wr.tid != 0);
        b->w = (struct timed_waiter){NULL, rw, TW_RWLOCK + k, 0, 0};
        struct task_syscall sc;
        if (start_timed_waiter(&t, &b->w) < 0)
            return -EAGAIN; /* b stays write-locked: left behind */
        if (wait_in_futex_within(b->w.tid, rw, sizeof *rw, &sc) == 0) {
            out->rw_seen[k] = 1;
            out->rw_op[k] = (int)sc.args[1];
            out->rw_val[k] = (int)sc.args[2];
            out->rw_pc[k] = sc.pc;
            out->rw_futex_off[k] = (long)(sc.args[0] - (uintptr_t)rw);
            if (readers) /* a blocked writer records nothing */
                out->rw_writer_recorded[k] = rw->__data.__cur_writer == 0;
            for (int i = 0; i < 32 && rw_fn[k]; i++) {
                Dl_info info;
                uintptr_t v = stack_word(sc.sp, i);
                if (dladdr((void *)v, &info) && info.dli_saddr == rw_fn[k]) {
                    out->rw_ret_slot[k] = i;
                    out->rw_ret[k] = v;
                    break;
                }
            }
        }
        int writer = wr.tid;
        if (readers ? pthread_rwlock_unlock(rw) == 0
                    : __atomic_compare_exchange_n(&rw->__data.__cur_writer, &writer, out->self_tid,
                                                  false, __ATOMIC_ACQ_REL, __ATOMIC_RELAXED) &&
                          pthread_rwlock_unlock(rw) == 0)
            for (int i = 0; i < 2000 && !out->rw_released[k]; i++) {
                out->rw_released[k] = __atomic_load_n(&b->w.phase, __ATOMIC_ACQUIRE) == 2;
                if (!out->rw_released[k])
                    usleep(1000);
            }
        if (!out->rw_released[k]) { /* stuck: leave it behind, say so */
            pthread_detach(t);
            return 0;
        }
        pthread_join(t, NULL);
        pthread_rwlock_destroy(rw);
        free(b);
    }
    for (int k = 0; k < CG_TIMED_PROBES; k++) {
        pthread_mutex_t m;
        pthread_mutexattr_t at;
        pthread_mutexattr_init(&at);
        pthread_mutexattr_settype(&at, k / 2);
        pthread_mutex_init(&m, &at);
        pthread_mutexattr_destroy(&at);
        pthread_mutex_lock(&m);
        struct timed_waiter w = {&m, NULL, k % 2 ? TW_CLOCKLOCK : TW_TIMEDLOCK, 0, 0};
        struct task_syscall sc;
        pthread_t t;
        if (start_timed_waiter(&t, &w) < 0) {
            pthread_mutex_unlock(&m);
            return -EAGAIN;
        }
        out->kind[k] = m.__data.__kind;
        out->owner_is_self[k] = m.__data.__owner == out->self_tid;
        if (wait_in_futex(w.tid, &m, &sc) == 0) {
            out->seen[k] = 1;
            out->op[k] = (int)sc.args[1];
            out->val[k] = (int)sc.args[2];
            out->pc[k] = sc.pc;
            /* The word where the rwlock waiters' return address is: the
               pc is the same (checked), so is the frame below it. */
            Dl_info info;
            out->ret_slot[k] = out->rw_ret_slot[0];
            out->ret[k] = out->rw_ret[0] ? stack_word(sc.sp, out->rw_ret_slot[0]) : 0;
            out->ret_in_libc[k] = out->ret[k] && dladdr((void *)out->ret[k], &info) &&
                                  info.dli_fbase == libc_info.dli_fbase;
        }
        pthread_mutex_unlock(&m);
        pthread_join(t, NULL);
        pthread_mutex_destroy(&m);
    }
    return 0;
}
