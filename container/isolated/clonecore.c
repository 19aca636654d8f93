/*
 * clonecore.c - the C core of cloneguard's --isolated mode.
 *
 * A "child" is a task made with clone3(CLONE_VM) and no CLONE_THREAD: its own
 * pid, signal dispositions and rlimits, but the container's address space.
 * glibc knows nothing of such a task, so this file gives it what
 * pthread_create would have: a TLS block with a struct pthread in it, a stack,
 * a robust-futex list, a locale.  Everything layout-dependent (offsets into
 * struct pthread, TLS offsets) comes from assumptions.py through struct
 * cg_layout; that module discovers each value and checks it against a live
 * thread before anything here runs.  x86_64 and glibc only.
 *
 * Threads and who may touch what:
 *   - The monitor thread (one, started by cg_start) performs every clone3,
 *     because PR_SET_PDEATHSIG fires when the *spawning thread* dies.  It
 *     waits on pidfds, reaps children and reports to Python through a pipe of
 *     fixed-size records.  It never takes the GIL.  It alone touches the child
 *     list (g_children) and cg_child.stop_reported.
 *   - Python threads call cg_spawn / cg_request_stop / cg_release; cffi
 *     releases the GIL around each call.
 *   - A child runs child_main on its own stack and TLS, then the Python
 *     callable under PyGILState_Ensure, then leaves with a raw SYS_exit.
 *
 * After a death, before reaping, the monitor calls gilrepair.c to undo what
 * the dead task left in CPython's GIL (see there).  Crash reports come from
 * the child itself (on_crash, on its own sigaltstack).
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <Python.h>
#include <asm/prctl.h>
#include <dlfcn.h>
#include <execinfo.h>
#include <errno.h>
#include <fcntl.h>
#include <sched.h>
#include <stdio.h>
#include <linux/futex.h>
#include <linux/sched.h> /* struct clone_args, CLONE_INTO_CGROUP, ... */
#include <locale.h>
#include <pthread.h>
#include <resolv.h>
#include <signal.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/mman.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "allocguard.h"
#include "clonecore.h"

#if !defined(__x86_64__)
#error "clonecore.c: x86_64 only (clone3 trampoline and TLS layout)"
#endif

/* ---------------------------------------------------------------------- */
/* Shapes shared with Python (mirrored in _build_core.py's cdef).          */

struct cg_layout {           /* byte offsets from the thread pointer (= TCB) */
    long tcb, self, multiple_threads, stack_guard, pointer_guard; /* tcbhead */
    long list, tid, robust_head, specific, specific_1stblock;    /* pthread */
    long rseq_cpu_id;        /* __rseq_offset + offsetof(struct rseq, cpu_id) */
    long resp_tls;           /* &__resp (initial-exec TLS in libc) - tp */
    long robust_futex_offset;/* robust_list_head.futex_offset glibc uses */
    long cleanup;            /* struct pthread.cleanup (pthread_cleanup_push) */
    long cond_cleanup;       /* address of glibc's condvar-wait cleanup
                                routine (cg_probe_condwait), 0: unknown */
};

struct cg_config {           /* per CloneCore; see core.Mitigations */
    int gil_repair;
    int condvar_repair;
    int crash_report;
    int jemalloc_own_arena;  /* without alloc_guard: arenas.create in the child */
    int jemalloc_tcache;
    int alloc_guard;         /* allocguard.c is preloaded: use it (see there) */
};

enum { CG_EV_DEATH = 1, CG_EV_STOP = 2, CG_EV_CLOSED = 3 };
struct cg_event {            /* one record on the event pipe: 40 bytes */
    uint32_t kind;
    int32_t pid;
    int32_t status;          /* death: si_status; stop: CG_STOP_* */
    int32_t code;            /* death: si_code (CLD_EXITED/KILLED/DUMPED),
                                0 if someone else reaped the child;
                                stop: the signal (0: asked by the parent) */
    uint64_t serial;
    int64_t t_ns;            /* CLOCK_MONOTONIC when the monitor noticed */
    uint32_t repairs;        /* death: CG_REPAIR_* (clonecore.h) */
    uint32_t alloc;          /* death: its allocator slot (low 16 bits, 0:
                                none) | CG_ALLOC_QUARANTINED */
};
#define CG_ALLOC_QUARANTINED (1u << 31)

enum { CG_STOP_NONE = 0, CG_STOP_PARENT = 1, CG_STOP_SIGNAL = 2 };
enum { CG_RUNNING = 0, CG_REAPED = 1 };
enum { CG_PY_NOT_YET = 0, CG_PY_INSIDE = 1, CG_PY_LEFT = 2 };
#define CG_FLAG_ALLOW_CORE 1  /* experiments only: leave RLIMIT_CORE alone */

struct cg_child {            /* control block, lives in container memory */
    /* read by Python */
    int pid;
    int pidfd;
    uint64_t serial;         /* Python's name for the child */
    int64_t start_ns;
    int state;               /* CG_RUNNING / CG_REAPED (atomic) */
    int stop_requested;      /* CG_STOP_* (atomic; child, parent, monitor) */
    int py_phase;            /* CG_PY_* (atomic; written by the child) */
    int stop_signal;         /* the signal that asked (atomic), 0: parent */
    int arena;               /* jemalloc arena the child bound to, -1: none */
    /* set up before the clone */
    PyObject *target;        /* borrowed: Python keeps it alive until reaped */
    PyThreadState *tstate;   /* made by cg_spawn, deleted by cg_release */
    int flags;
    int cgroup_fd;           /* -1: stay in the container's cgroup */
    int parent_tgid;
    char *map;               /* guard page + stack */
    size_t map_len, stack_size;
    char *alt;               /* guard page + signal stack (crash reports) */
    size_t alt_len;
    char *tcb;               /* from _dl_allocate_tls (or ctx->tcb) */
    struct cg_ctx *ctx;      /* with the allocator guard: its context */
    /* monitor-only */
    int stop_reported;
    int repair_done;         /* gilrepair has looked at this dead child */
    uint32_t repairs;        /* what it repaired for it */
    int quarantined;         /* it died inside the allocator */
    struct cg_child *next;
    /* the child's own resolver state, as start_thread gives each thread */
    struct __res_state res;
};

/* ---------------------------------------------------------------------- */
/* Globals                                                                 */

static struct cg_layout L;
static struct cg_config C;
static void *(*dl_allocate_tls)(void *);
static void (*dl_deallocate_tls)(void *, bool);

static int g_epfd = -1, g_wakefd = -1, g_cmd[2] = {-1, -1}, g_ev[2] = {-1, -1};
static pthread_t g_monitor;
static int g_started;
static struct cg_child *g_children;   /* monitor-only */

/* Which child the current task is.  initial-exec so the SIGTERM handler
   reads it with a plain %fs-relative load (no __tls_get_addr, no malloc);
   the static TLS block is part of every _dl_allocate_tls. */
static __thread struct cg_child *cg_self __attribute__((tls_model("initial-exec")));
/* The signal a crash report is about (for its watchdog, on the same thread). */
static __thread int cg_crash_sig __attribute__((tls_model("initial-exec")));

/* jemalloc's mallctl when jemalloc is the process's malloc, else NULL. */
typedef int (*mallctl_fn)(const char *, void *, size_t *, void *, size_t);
static mallctl_fn g_mallctl;

static char TAG_CMD, TAG_WAKE;        /* epoll tags that are not children */

#define AT(base, off, type) (*(type *)((char *)(base) + (off)))

/* The allocator guard's entry points (allocguard.h), when it is preloaded. */
static struct {
    cga_activate_fn activate;
    cga_slot_new_fn slot_new;
    cga_warm_fn warm;
    cga_slot_bind_fn slot_bind;
    cga_child_start_fn child_start;
    cga_slot_retire_fn slot_retire;
    cga_slot_stats_fn slot_stats;
} G;

/* With the guard, a child runs in a *context*: a TLS block (struct pthread
   + static TLS) and the allocator slot bound to it, whose thread cache,
   arena binding and (glibc) arena live in that TLS block.  A context whose
   child ended outside the allocator is reused by the next child, with all
   of that in place; one whose child died inside the allocator is never
   touched again (its TLS block stays allocated: jemalloc keeps a list of
   every thread's data, this one included). */
struct cg_ctx {
    char *tcb;
    int slot;
    struct cg_ctx *next;
};
static pthread_mutex_t g_pool_lock = PTHREAD_MUTEX_INITIALIZER; /* container threads only */
static struct cg_ctx *g_pool;          /* idle contexts, most recent first */

static int64_t mono_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* ---------------------------------------------------------------------- */
/* Small helpers assumptions.py uses to discover and check the layout.     */

uintptr_t cg_thread_pointer(void)
{
    unsigned long fs = 0;
    syscall(SYS_arch_prctl, ARCH_GET_FS, &fs);
    return fs;
}

uintptr_t cg_robust_list_head(void)   /* what the kernel has for this task */
{
    void *head = NULL;
    size_t len = 0;
    if (syscall(SYS_get_robust_list, 0, &head, &len) != 0)
        return 0;
    return (uintptr_t)head;
}

long cg_gettid(void) { return syscall(SYS_gettid); }

void *cg_lookup(const char *name, const char *version)
{
    return version ? dlvsym(RTLD_DEFAULT, name, version)
                   : dlsym(RTLD_DEFAULT, name);
}

long cg_mutex_futex_offset(void)   /* glibc: futex word minus list.__next */
{
    return (long)offsetof(pthread_mutex_t, __data.__lock) -
           (long)offsetof(pthread_mutex_t, __data.__list.__next);
}

int cg_probe_clone3(void)   /* 0 if the kernel has clone3, else errno */
{
    /* A size of 0 is below CLONE_ARGS_SIZE_VER0: EINVAL if clone3 exists. */
    long r = syscall(SYS_clone3, NULL, (size_t)0);
    return (r < 0 && errno == EINVAL) ? 0 : (r < 0 ? errno : EEXIST);
}

/* A pthread_cond_wait that is blocked, seen from outside: glibc 2.36 pushes
   a cleanup record (struct pthread.cleanup) whose argument says which
   condvar, which mutex and which position it waits at, and it holds a
   reference on its condvar group meanwhile.  gilrepair.c relies on all of
   that for dead waiters; this probes it on a live pthread at start-up. */
struct cg_condwait_probe {
    uintptr_t routine;       /* the cleanup routine the waiter pushed */
    int found;               /* TCB+cleanup became non-NULL while it waited */
    int buf_on_stack;        /* the record lies on the waiter's stack */
    int cbuf_matches;        /* its argument names our cond and mutex */
    int wseq_matches;        /* argument.wseq + 2 == cond.__wseq (1 waiter) */
    int holds_ref;           /* cond.__g_refs[group] == 2 while it waits */
    int routine_in_libc;
    int cleared_after;       /* TCB+cleanup is back to what it was before */
};

struct probe_arg {
    pthread_mutex_t m;
    pthread_cond_t cv;
    int go, ready;
    long cleanup_off;
    char *sp;
    char *volatile tcb;
    void *before, *after;    /* its .cleanup before / after the wait */
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
    for (int i = 0; i < 2000 && (!buf || buf == a.before); i++) {   /* ~2 s */
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
        out->buf_on_stack = (char *)buf > lo && (char *)buf < hi &&
                            (char *)cb > lo && (char *)cb < hi;
        if (out->buf_on_stack) {
            out->routine = (uintptr_t)buf->__routine;
            out->cbuf_matches = cb->cond == &a.cv && cb->mutex == &a.m;
            out->wseq_matches = cb->wseq + 2 == a.cv.__data.__wseq.__value64;
            out->holds_ref = a.cv.__data.__g_refs[cb->wseq & 1] == 2;
            Dl_info info;
            out->routine_in_libc = dladdr((void *)out->routine, &info) &&
                                   info.dli_fname && strstr(info.dli_fname, "libc.so");
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
static mallctl_fn find_mallctl(void)
{
    mallctl_fn f = (mallctl_fn)dlsym(RTLD_DEFAULT, "mallctl");
    Dl_info a, b;
    /* jemalloc must be the malloc in use, not merely loaded. */
    if (!f || !dladdr((void *)f, &a) ||
        !dladdr(dlsym(RTLD_DEFAULT, "malloc"), &b) || a.dli_fbase != b.dli_fbase)
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

/* Whether the calling thread has a jemalloc thread cache: 1/0; -1 without
   jemalloc. */
int cg_jemalloc_thread_tcache(void)
{
    mallctl_fn f = find_mallctl();
    bool on;
    size_t sz = sizeof on;
    if (!f || f("thread.tcache.enabled", &on, &sz, NULL, 0) != 0)
        return -1;
    return on;
}

/* The jemalloc arena the calling thread allocates from; -1 without
   jemalloc. */
int cg_jemalloc_thread_arena(void)
{
    mallctl_fn f = find_mallctl();
    unsigned a;
    size_t sz = sizeof a;
    if (!f || f("thread.arena", &a, &sz, NULL, 0) != 0)
        return -1;
    return (int)a;
}

/* ---------------------------------------------------------------------- */
/* The clone3 trampoline.
 *
 *   long cg_clone3(struct clone_args *args, size_t size,
 *                  int (*fn)(void *), void *arg);
 *
 * The child comes back from the syscall on its new stack (the kernel sets
 * rsp = stack + stack_size, page aligned, hence 16-byte aligned for the call)
 * with every register but rax/rcx/r11 as the parent had them.  So fn and arg
 * travel in r8/r9.  The child must not return into the parent's frame: it
 * calls fn and ends with a raw SYS_exit, which ends only this task and runs
 * no atexit handler and no stdio flush in the shared address space.
 */
long cg_clone3(struct clone_args *args, size_t size, int (*fn)(void *), void *arg);
__asm__(
    ".text\n"
    ".p2align 4\n"
    ".type cg_clone3, @function\n"
    "cg_clone3:\n"
    "    mov %rdx, %r8\n"            /* fn  */
    "    mov %rcx, %r9\n"            /* arg */
    "    mov $" "435" ", %eax\n"     /* SYS_clone3 (x86_64) */
    "    syscall\n"
    "    test %rax, %rax\n"
    "    jnz 1f\n"                   /* parent (pid) or error (-errno) */
    "    xor %ebp, %ebp\n"           /* child: outermost frame */
    "    mov %r9, %rdi\n"
    "    call *%r8\n"
    "    mov %eax, %edi\n"
    "    mov $60, %eax\n"            /* SYS_exit */
    "    syscall\n"
    "    hlt\n"
    "1:  ret\n"
    ".size cg_clone3, .-cg_clone3\n");
_Static_assert(SYS_clone3 == 435, "SYS_clone3 number used in the trampoline");

/* ---------------------------------------------------------------------- */
/* A fresh TLS block + struct pthread for a child, filled in the parent.    */

/* What a child may leave behind in its struct pthread that the next child
   in the same TLS block must not inherit. */
static void tls_reset(char *tcb)
{
    /* Empty robust list: list points at the head itself. */
    AT(tcb, L.robust_head, void *) = tcb + L.robust_head;
    AT(tcb, L.robust_head + 8, long) = L.robust_futex_offset;
    AT(tcb, L.robust_head + 16, void *) = NULL;
    /* No pthread_cleanup record (one is left by a death in a condvar wait,
       and gilrepair.c reads it). */
    AT(tcb, L.cleanup, void *) = NULL;
}

static char *tls_new(void)
{
    char *tcb = dl_allocate_tls(NULL);   /* struct pthread zeroed, dtv set */
    if (!tcb)
        return NULL;
    char *me = (char *)cg_thread_pointer();

    AT(tcb, L.tcb, void *) = tcb;        /* THREAD_SELF reads these */
    AT(tcb, L.self, void *) = tcb;
    /* x86 catomic_* skip the lock prefix when this is 0: must be 1. */
    AT(tcb, L.multiple_threads, int) = 1;
    /* The canary only needs to be stable per task, but pointer_guard must
       equal every other thread's: mangled pointers (setjmp buffers, atexit
       and dl handlers) are shared. */
    AT(tcb, L.stack_guard, uintptr_t) = AT(me, L.stack_guard, uintptr_t);
    AT(tcb, L.pointer_guard, uintptr_t) = AT(me, L.pointer_guard, uintptr_t);
    /* Not on GL(dl_stack_used): an empty self-linked list keeps list_del
       (fork in a child) harmless. */
    AT(tcb, L.list, void *) = tcb + L.list;
    AT(tcb, L.list + 8, void *) = tcb + L.list;
    /* pthread_getspecific for keys < 32 goes through specific[0]. */
    AT(tcb, L.specific, void *) = tcb + L.specific_1stblock;
    /* rseq is not registered for the child: RSEQ_CPU_ID_REGISTRATION_FAILED
       makes sched_getcpu fall back to the syscall. */
    AT(tcb, L.rseq_cpu_id, int32_t) = -2;
    tls_reset(tcb);
    /* tid is written by the kernel (CLONE_{CHILD,PARENT}_SETTID). */
    return tcb;
}

/* ---------------------------------------------------------------------- */
/* The child.                                                              */

/* SIGTERM and SIGINT (Ctrl-C signals the whole foreground process group,
   children included): set the stop flag once, remember which signal, wake
   the monitor.  A process-directed signal can land on any thread of the
   child, including threads it created, whose cg_self is NULL: those pass it
   on to the child's main task (tid == pid). */
static void on_stop_signal(int sig)
{
    int saved = errno;
    struct cg_child *c = cg_self;
    if (!c) {
        syscall(SYS_tgkill, getpid(), getpid(), sig);
    } else {
        int zero = 0, none = CG_STOP_NONE;
        __atomic_compare_exchange_n(&c->stop_signal, &zero, sig, false,
                                    __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST);
        if (__atomic_compare_exchange_n(&c->stop_requested, &none,
                                        CG_STOP_SIGNAL, false,
                                        __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST)) {
            uint64_t one = 1;   /* eventfd write: async-signal-safe */
            if (write(g_wakefd, &one, sizeof one) < 0) { /* nothing to do */ }
        }
    }
    errno = saved;
}

/* ---- crash reports --------------------------------------------------- */

static const int crash_signals[] = {SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGABRT};

struct out { char b[256]; size_t n; };

static void out_s(struct out *o, const char *s)
{
    while (*s && o->n < sizeof o->b)
        o->b[o->n++] = *s++;
}

static void out_u(struct out *o, unsigned long v, unsigned base)
{
    char tmp[24];
    int i = 0;
    if (base == 16)
        out_s(o, "0x");
    do
        tmp[i++] = "0123456789abcdef"[v % base];
    while ((v /= base) && i < (int)sizeof tmp);
    while (i && o->n < sizeof o->b)
        o->b[o->n++] = tmp[--i];
}

static void out_flush(struct out *o)
{
    size_t done = 0;
    while (done < o->n) {
        ssize_t w = write(2, o->b + done, o->n - done);
        if (w <= 0 && errno != EINTR)
            break;
        if (w > 0)
            done += (size_t)w;
    }
    o->n = 0;
}

/* The report did not finish within 2 s (the symboliser waits for the
   dynamic linker's lock, say): die of the signal we were reporting.  It is
   SIG_DFL again (SA_RESETHAND) and blocked while its handler runs. */
static void on_crash_timeout(int unused)
{
    (void)unused;
    int sig = cg_crash_sig;
    sigset_t s;
    sigemptyset(&s);
    sigaddset(&s, sig);
    syscall(SYS_tgkill, getpid(), syscall(SYS_gettid), sig);
    sigprocmask(SIG_UNBLOCK, &s, NULL);
}

/* One report on fd 2, then the same death as without us: the handler was
   installed SA_RESETHAND, so the disposition is SIG_DFL again, and the
   signal is re-sent to this thread; it is delivered (and kills the child)
   as the handler returns.  A fault inside here kills at once (SIG_DFL).
   Everything used is async-signal-safe, except backtrace (its unwinder was
   loaded by cg_start; on glibc 2.35+ it finds FDEs without locks) and
   backtrace_symbols_fd (dladdr, which takes the loader's lock: hence the
   watchdog timer). */
static void on_crash(int sig, siginfo_t *si, void *uc_)
{
    ucontext_t *uc = uc_;
    int saved = errno;
    cg_crash_sig = sig;
    pid_t pid = getpid(), tid = (pid_t)syscall(SYS_gettid);

    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_crash_timeout;
    sigaction(SIGALRM, &sa, NULL);
    struct sigevent sev;
    memset(&sev, 0, sizeof sev);
    sev.sigev_notify = SIGEV_THREAD_ID;
    sev.sigev_signo = SIGALRM;
    sev._sigev_un._tid = tid;   /* sigev_notify_thread_id */
    int timer;
    if (syscall(SYS_timer_create, CLOCK_MONOTONIC, &sev, &timer) == 0) {
        struct itimerspec its = {{0, 0}, {2, 0}};
        syscall(SYS_timer_settime, timer, 0, &its, NULL);
    }

    struct out o = {.n = 0};
    const char *abbrev = sigabbrev_np(sig);
    out_s(&o, "cloneguard: pid ");
    out_u(&o, (unsigned long)pid, 10);
    out_s(&o, " caught SIG");
    out_s(&o, abbrev ? abbrev : "?");
    out_s(&o, " at ");
    if (si->si_code > 0)                 /* raised by a fault */
        out_u(&o, (uintptr_t)si->si_addr, 16);
    else                                 /* sent: there is no address */
        out_s(&o, "-");
    out_s(&o, " (pc ");
    out_u(&o, (unsigned long)uc->uc_mcontext.gregs[REG_RIP], 16);
    out_s(&o, ")\ncloneguard: si_code ");
    if (si->si_code < 0) {
        out_s(&o, "-");
        out_u(&o, (unsigned long)-si->si_code, 10);
    } else {
        out_u(&o, (unsigned long)si->si_code, 10);
    }
    if (si->si_code <= 0) {
        out_s(&o, " (sent by pid ");
        out_u(&o, (unsigned long)si->si_pid, 10);
        out_s(&o, ")");
    }
    if (tid != pid) {
        out_s(&o, ", thread ");
        out_u(&o, (unsigned long)tid, 10);
    }
    out_s(&o, "\ncloneguard: native stack:\n");
    out_flush(&o);
    void *frames[64];
    int n = backtrace(frames, 64);
    backtrace_symbols_fd(frames, n, 2);
    out_s(&o, "cloneguard: Python ");
    out_flush(&o);
    cg_dump_py_stack(2);   /* "Stack (most recent call first): ..." */

    syscall(SYS_tgkill, pid, tid, sig);
    errno = saved;
}

static void install_crash_handlers(struct cg_child *c)
{
    stack_t ss = {.ss_sp = c->alt + (size_t)sysconf(_SC_PAGESIZE),
                  .ss_size = c->alt_len - (size_t)sysconf(_SC_PAGESIZE),
                  .ss_flags = 0};
    if (sigaltstack(&ss, NULL) < 0)
        return;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_sigaction = on_crash;
    sa.sa_flags = SA_SIGINFO | SA_ONSTACK | SA_RESETHAND;
    sigemptyset(&sa.sa_mask);
    for (size_t i = 0; i < sizeof crash_signals / sizeof crash_signals[0]; i++)
        sigaction(crash_signals[i], &sa, NULL);
}

/* jemalloc: an arena of its own for this child (a lock it dies holding in
   malloc then stops only those who free its blocks, not everyone who
   allocates), optionally no thread cache (no blocks sit cached in a dead
   child). */
static void jemalloc_setup(struct cg_child *c)
{
    c->arena = -1;
    if (!g_mallctl)
        return;
    if (C.jemalloc_own_arena) {
        unsigned a;
        size_t sz = sizeof a;
        if (g_mallctl("arenas.create", &a, &sz, NULL, 0) == 0 &&
            g_mallctl("thread.arena", NULL, NULL, &a, sizeof a) == 0)
            c->arena = (int)a;
    }
    if (!C.jemalloc_tcache) {
        bool off = false;
        g_mallctl("thread.tcache.enabled", NULL, NULL, &off, sizeof off);
    }
}

static int exit_code_of_current_exception(void)   /* GIL held */
{
    if (!PyErr_ExceptionMatches(PyExc_SystemExit)) {
        /* Never PyErr_Print: it sets sys.last_* in the shared interpreter
           and would exit the *container* on SystemExit. */
        PyErr_PrintEx(0);
        return 1;
    }
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyErr_NormalizeException(&type, &value, &tb);
    PyObject *code = value ? PyObject_GetAttrString(value, "code") : NULL;
    int rc = 1;
    if (code == NULL)
        PyErr_Clear();
    else if (code == Py_None)
        rc = 0;
    else if (PyLong_Check(code))
        rc = (int)PyLong_AsLong(code);
    else
        PyObject_Print(code, stderr, Py_PRINT_RAW), fputc('\n', stderr);
    if (PyErr_Occurred())
        PyErr_Clear();
    Py_XDECREF(code);
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(tb);
    return rc;
}

static int child_main(void *arg)
{
    struct cg_child *c = arg;

    /* 1. Core dumps off for this thread group (rlimits are per thread
       group, so the container keeps its own).  A dump would write the whole
       shared address space.  1, not 0: below the minimum dump size for a
       file core_pattern, and the "don't dump" value for a pipe one. */
    if (!(c->flags & CG_FLAG_ALLOW_CORE)) {
        struct rlimit no_core = {1, 1};
        syscall(SYS_prlimit64, 0, RLIMIT_CORE, &no_core, NULL);
    }
    /* 2. The kernel marks robust mutexes we hold as owner-died on our exit
       only if it knows our list.  Must be done by this task itself. */
    syscall(SYS_set_robust_list, c->tcb + L.robust_head,
            sizeof(struct robust_list_head));
    /* 2b. With the allocator guard: threads we create find our slot by pid. */
    if (c->ctx)
        G.child_start();
    /* 3. Locale: the fresh TLS has no ctype tables; uselocale sets them. */
    uselocale(LC_GLOBAL_LOCALE);
    AT(c->tcb, L.resp_tls, struct __res_state *) = &c->res;
    /* 4. Die with the monitor thread (= the container).  If it is already
       gone we have been reparented: leave. */
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != c->parent_tgid)
        return 127;
    /* 5. Graceful stop: our own SIGTERM/SIGINT handler (CLONE_CLEAR_SIGHAND
       left every handler at SIG_DFL); crash reports on a stack of our own;
       the allocator; then unblock what the monitor blocked. */
    cg_self = c;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_stop_signal;
    sa.sa_flags = SA_RESTART;
    sigemptyset(&sa.sa_mask);
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    if (C.crash_report)
        install_crash_handlers(c);
    if (!c->ctx)
        jemalloc_setup(c);
    sigset_t none;
    sigemptyset(&none);
    sigprocmask(SIG_SETMASK, &none, NULL);

    /* 6. Python, in the thread state the parent made for us (so we never
       take the runtime's HEAD_LOCK, which has no owner to repair): bind it
       to this task, take the GIL, run, clear it and drop the GIL.  release()
       deletes it. */
    __atomic_store_n(&c->py_phase, CG_PY_INSIDE, __ATOMIC_RELEASE);
    cg_tstate_bind(c->tstate);
    PyEval_RestoreThread(c->tstate);
    PyObject *r = PyObject_CallNoArgs(c->target);
    int code = 0;
    if (r)
        Py_DECREF(r);
    else
        code = exit_code_of_current_exception();
    PyThreadState_Clear(c->tstate);
    PyEval_SaveThread();
    __atomic_store_n(&c->py_phase, CG_PY_LEFT, __ATOMIC_RELEASE);
    return code;                         /* trampoline: SYS_exit(code) */
}

int cg_self_stop_requested(void)   /* -1 when not called from a child */
{
    struct cg_child *c = cg_self;
    return c ? __atomic_load_n(&c->stop_requested, __ATOMIC_ACQUIRE) : -1;
}

/* ---------------------------------------------------------------------- */
/* The monitor thread.                                                     */

enum { CMD_SPAWN = 1, CMD_STOP = 2 };
struct cg_cmd {              /* lives on the caller's stack */
    int op;
    struct cg_child *child;
    int result;
    uint32_t done;           /* futex word */
};

static void cmd_finish(struct cg_cmd *cmd, int result)
{
    cmd->result = result;
    __atomic_store_n(&cmd->done, 1, __ATOMIC_RELEASE);
    /* The caller may already have returned; a wake on a stale address is a
       harmless spurious wake-up. */
    syscall(SYS_futex, &cmd->done, FUTEX_WAKE_PRIVATE, 1, NULL, NULL, 0);
}

static int submit(struct cg_cmd *cmd)   /* from any thread; blocks */
{
    /* 8-byte writes to a pipe are atomic: no lock to be left held. */
    ssize_t n;
    do
        n = write(g_cmd[1], &cmd, sizeof cmd);
    while (n < 0 && errno == EINTR);
    if (n != sizeof cmd)
        return -EPIPE;
    while (__atomic_load_n(&cmd->done, __ATOMIC_ACQUIRE) == 0)
        syscall(SYS_futex, &cmd->done, FUTEX_WAIT_PRIVATE, 0, NULL, NULL, 0);
    return cmd->result;
}

static void emit(uint32_t kind, const struct cg_child *c, int status,
                 int code, int64_t t, uint32_t repairs)
{
    uint32_t alloc = 0;
    if (c && c->ctx)
        alloc = (uint32_t)c->ctx->slot | (c->quarantined ? CG_ALLOC_QUARANTINED : 0);
    struct cg_event ev = {kind, c ? c->pid : 0, status, code,
                          c ? c->serial : 0, t, repairs, alloc};
    const char *p = (const char *)&ev;
    size_t left = sizeof ev;
    while (left) {   /* blocks if Python lags >2048 records behind */
        ssize_t n = write(g_ev[1], p, left);
        if (n < 0 && errno == EINTR)
            continue;
        if (n < 0)
            return;
        p += n, left -= (size_t)n;
    }
}

static void report_stop(struct cg_child *c, int64_t t)
{
    int s = __atomic_load_n(&c->stop_requested, __ATOMIC_ACQUIRE);
    if (s != CG_STOP_NONE && !c->stop_reported) {
        c->stop_reported = 1;
        emit(CG_EV_STOP, c, s, __atomic_load_n(&c->stop_signal, __ATOMIC_ACQUIRE),
             t, 0);
    }
}

static int do_spawn(struct cg_child *c)
{
    struct clone_args a;
    memset(&a, 0, sizeof a);
    a.flags = CLONE_VM | CLONE_FS | CLONE_FILES | CLONE_PIDFD | CLONE_SETTLS |
              CLONE_CLEAR_SIGHAND | CLONE_CHILD_SETTID | CLONE_PARENT_SETTID;
    a.pidfd = (uintptr_t)&c->pidfd;
    a.child_tid = a.parent_tid = (uintptr_t)(c->tcb + L.tid);
    a.exit_signal = SIGCHLD;
    a.stack = (uintptr_t)(c->map + (c->map_len - c->stack_size));
    a.stack_size = c->stack_size;
    a.tls = (uintptr_t)c->tcb;
    if (c->cgroup_fd >= 0) {
        a.flags |= CLONE_INTO_CGROUP;
        a.cgroup = (uint64_t)c->cgroup_fd;
    }
    c->parent_tgid = getpid();
    c->start_ns = mono_ns();

    long pid = cg_clone3(&a, sizeof a, child_main, c);
    if (pid < 0)
        return (int)pid;
    c->pid = (int)pid;

    struct epoll_event ev = {.events = EPOLLIN, .data.ptr = c};
    if (epoll_ctl(g_epfd, EPOLL_CTL_ADD, c->pidfd, &ev) < 0) {
        int err = errno;   /* cannot watch it: do not let it run */
        siginfo_t si;
        syscall(SYS_pidfd_send_signal, c->pidfd, SIGKILL, NULL, 0);
        waitid((idtype_t)P_PIDFD, (id_t)c->pidfd, &si, WEXITED | __WALL);
        close(c->pidfd);
        return -err;
    }
    c->next = g_children;
    g_children = c;
    return 0;
}

/* Dead but not yet reaped (or reaped by someone else): its tid cannot have
   been reused. */
static bool child_is_dead(struct cg_child *c)
{
    siginfo_t si;
    memset(&si, 0, sizeof si);
    if (waitid((idtype_t)P_PIDFD, (id_t)c->pidfd, &si,
               WEXITED | __WALL | WNOHANG | WNOWAIT) < 0)
        return errno == ECHILD;
    return si.si_pid != 0;
}

/* Undo what dead children left in the GIL (gilrepair.c): every dead child
   not looked at yet, so that one repair never waits for a lock or a
   condvar reference another dead child holds. */
static void repair_after_death(struct cg_child *reaped)
{
    if (!C.gil_repair && !C.condvar_repair)
        return;
    struct cg_dead d[32];
    struct cg_child *who[32];
    int n = 0;
    for (struct cg_child *c = g_children; c && n < 32; c = c->next)
        if (!c->repair_done && (c == reaped || child_is_dead(c))) {
            d[n] = (struct cg_dead){c->pid, c->tcb, c->map, c->map + c->map_len, 0};
            who[n++] = c;
        }
    struct cg_repair_cfg cfg = {C.gil_repair, C.condvar_repair, L.cleanup,
                                (uintptr_t)L.cond_cleanup};
    uint32_t misc = cg_gil_repair(d, n, &cfg);
    for (int i = 0; i < n; i++) {
        who[i]->repairs |= d[i].repairs;
        who[i]->repair_done = 1;
    }
    reaped->repairs |= misc;
}

static void reap(struct cg_child *c, int64_t t)
{
    siginfo_t si;
    memset(&si, 0, sizeof si);
    /* WNOWAIT: look, repair, and only then reap (the pid stays ours). */
    int r = waitid((idtype_t)P_PIDFD, (id_t)c->pidfd, &si,
                   WEXITED | __WALL | WNOHANG | WNOWAIT);
    if (r == 0 && si.si_pid == 0)
        return;                  /* readable but not yet waitable */
    if (r < 0 && errno != ECHILD)
        return;
    /* ECHILD: something else in the container reaped it (a waitpid(-1)).
       It is dead, the status is lost: report code 0. */
    int status = r == 0 ? si.si_status : -1;
    int code = r == 0 ? si.si_code : 0;

    repair_after_death(c);
    /* Every task of the child is gone: whether it died inside the allocator
       is settled now (before anything hears of the death). */
    if (c->ctx)
        c->quarantined = G.slot_retire(c->ctx->slot, c->ctx->tcb);
    if (r == 0) {
        siginfo_t gone;
        memset(&gone, 0, sizeof gone);
        waitid((idtype_t)P_PIDFD, (id_t)c->pidfd, &gone, WEXITED | __WALL | WNOHANG);
    }
    report_stop(c, t);           /* never after the death record */
    epoll_ctl(g_epfd, EPOLL_CTL_DEL, c->pidfd, NULL);
    for (struct cg_child **p = &g_children; *p; p = &(*p)->next)
        if (*p == c) {
            *p = c->next;
            break;
        }
    __atomic_store_n(&c->state, CG_REAPED, __ATOMIC_RELEASE);
    emit(CG_EV_DEATH, c, status, code, t, c->repairs);
}

static void *monitor_main(void *unused)
{
    (void)unused;
    struct epoll_event evs[32];
    for (;;) {
        int n = epoll_wait(g_epfd, evs, 32, -1);
        if (n < 0)
            continue;                    /* EINTR; all signals are blocked */
        int64_t t = mono_ns();
        /* Commands and stop notices first, deaths second: a stop notice of
           a child must reach Python before its death record. */
        for (int i = 0; i < n; i++) {
            if (evs[i].data.ptr == &TAG_WAKE) {
                uint64_t v;
                if (read(g_wakefd, &v, sizeof v) < 0) { /* EAGAIN */ }
                for (struct cg_child *c = g_children; c; c = c->next)
                    report_stop(c, t);
            } else if (evs[i].data.ptr == &TAG_CMD) {
                struct cg_cmd *cmd;
                if (read(g_cmd[0], &cmd, sizeof cmd) != sizeof cmd)
                    continue;
                if (cmd->op == CMD_SPAWN) {
                    cmd_finish(cmd, do_spawn(cmd->child));
                } else if (cmd->op == CMD_STOP) {
                    if (g_children) {
                        cmd_finish(cmd, -EBUSY);
                    } else {
                        emit(CG_EV_CLOSED, NULL, 0, 0, t, 0);
                        cmd_finish(cmd, 0);
                        return NULL;
                    }
                }
            }
        }
        for (int i = 0; i < n; i++)
            if (evs[i].data.ptr != &TAG_WAKE && evs[i].data.ptr != &TAG_CMD)
                reap(evs[i].data.ptr, t);
    }
}

static void close_fds(void)
{
    int *fds[] = {&g_epfd, &g_wakefd, &g_cmd[0], &g_cmd[1], &g_ev[1]};
    for (size_t i = 0; i < sizeof fds / sizeof fds[0]; i++)
        if (*fds[i] >= 0)
            close(*fds[i]), *fds[i] = -1;
}

/* ---------------------------------------------------------------------- */
/* The allocator guard's contexts.                                         */

static int guard_start(void)
{
    if (G.activate)
        return 0;                        /* one activation per process */
#define FIND(field, name) G.field = (void *)dlsym(RTLD_DEFAULT, name)
    FIND(activate, "cga_activate");
    FIND(slot_new, "cga_slot_new");
    FIND(warm, "cga_warm");
    FIND(slot_bind, "cga_slot_bind");
    FIND(child_start, "cga_child_start");
    FIND(slot_retire, "cga_slot_retire");
    FIND(slot_stats, "cga_slot_stats");
#undef FIND
    if (!G.activate || !G.slot_new || !G.warm || !G.slot_bind ||
        !G.child_start || !G.slot_retire || !G.slot_stats) {
        memset(&G, 0, sizeof G);
        return -ENOENT;                  /* not preloaded */
    }
    int r = G.activate(getpid());
    if (r < 0 && r != -EALREADY) {
        memset(&G, 0, sizeof G);
        return r;
    }
    return 0;
}

/* Run cga_warm(slot) as the context's own task would: with its TLS block as
   this thread's, for the few calls that set up its allocator state.  All
   signals stay blocked meanwhile (no handler may run on a borrowed TLS);
   nothing here touches TLS itself across the switch. */
static __attribute__((noinline)) int ctx_warm(struct cg_ctx *x)
{
    sigset_t all, old;
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    uintptr_t mine = cg_thread_pointer();
    syscall(SYS_arch_prctl, ARCH_SET_FS, (unsigned long)x->tcb);
    int r = G.warm(x->slot);
    syscall(SYS_arch_prctl, ARCH_SET_FS, (unsigned long)mine);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    return r;
}

static struct cg_ctx *ctx_take(void)
{
    pthread_mutex_lock(&g_pool_lock);
    struct cg_ctx *x = g_pool;
    if (x)
        g_pool = x->next;
    pthread_mutex_unlock(&g_pool_lock);
    if (x)
        return x;
    x = calloc(1, sizeof *x);
    if (!x)
        return NULL;
    x->tcb = tls_new();
    x->slot = x->tcb ? G.slot_new() : -ENOMEM;
    if (x->slot < 0 || ctx_warm(x) < 0) {
        /* A slot made and not warmed stays unused: never handed out. */
        if (x->tcb)
            dl_deallocate_tls(x->tcb, true);
        free(x);
        return NULL;
    }
    return x;
}

static void ctx_put(struct cg_ctx *x)
{
    pthread_mutex_lock(&g_pool_lock);
    x->next = g_pool;
    g_pool = x;
    pthread_mutex_unlock(&g_pool_lock);
}

/* What an allocator slot holds (allocguard.h); -ENOENT without the guard. */
int cg_alloc_slot_stats(int slot, struct cga_slot_stats *out)
{
    return G.slot_stats ? G.slot_stats(slot, out) : -ENOENT;
}

/* Start the monitor.  *event_fd receives the read end of the event pipe,
   which Python owns (and closes after cg_stop). */
int cg_start(const struct cg_layout *layout, const struct cg_config *cfg,
             int *event_fd)
{
    if (g_started)
        return -EALREADY;
    C = *cfg;
    g_mallctl = find_mallctl();
    if (C.crash_report) {
        /* The first backtrace() dlopens libgcc_s: never in a handler. */
        void *warm[4];
        backtrace(warm, 4);
    }
    dl_allocate_tls = (void *(*)(void *))dlvsym(RTLD_DEFAULT,
                                 "_dl_allocate_tls", "GLIBC_PRIVATE");
    dl_deallocate_tls = (void (*)(void *, bool))dlvsym(RTLD_DEFAULT,
                                 "_dl_deallocate_tls", "GLIBC_PRIVATE");
    if (!dl_allocate_tls || !dl_deallocate_tls)
        return -ENOSYS;
    L = *layout;
    if (C.alloc_guard) {
        int r = guard_start();
        if (r < 0)
            return r;
    }

    g_epfd = epoll_create1(EPOLL_CLOEXEC);
    g_wakefd = eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (g_epfd < 0 || g_wakefd < 0 || pipe2(g_cmd, O_CLOEXEC) < 0 ||
        pipe2(g_ev, O_CLOEXEC) < 0) {
        int err = errno;
        close_fds();
        return -err;
    }
    struct epoll_event e1 = {.events = EPOLLIN, .data.ptr = &TAG_CMD};
    struct epoll_event e2 = {.events = EPOLLIN, .data.ptr = &TAG_WAKE};
    epoll_ctl(g_epfd, EPOLL_CTL_ADD, g_cmd[0], &e1);
    epoll_ctl(g_epfd, EPOLL_CTL_ADD, g_wakefd, &e2);

    /* The monitor runs with every signal blocked (process-directed signals
       go to other threads); children inherit that mask and clear it. */
    sigset_t all, old;
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    int err = pthread_create(&g_monitor, NULL, monitor_main, NULL);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (err) {
        close(g_ev[0]);
        g_ev[0] = -1;
        close_fds();
        return -err;
    }
    g_started = 1;
    *event_fd = g_ev[0];
    g_ev[0] = -1;
    return 0;
}

/* Stop the monitor: -EBUSY while any child is unreaped. */
int cg_stop(void)
{
    if (!g_started)
        return -EALREADY;
    struct cg_cmd cmd = {CMD_STOP, NULL, 0, 0};
    int r = submit(&cmd);
    if (r != 0)
        return r;
    pthread_join(g_monitor, NULL);
    close_fds();
    g_started = 0;
    return 0;
}

/* ---------------------------------------------------------------------- */
/* Children, from Python.                                                  */

static void forget_thread_state(PyThreadState *t);

/* The child's TLS block, after it ended or never started: back to the pool
   with its context, kept for good when it died inside the allocator, freed
   when there is no guard. */
static void tls_give_back(struct cg_child *c)
{
    if (c->ctx) {
        if (c->quarantined) {
            free(c->ctx);                /* the TLS block itself stays */
        } else {
            G.slot_retire(c->ctx->slot, c->ctx->tcb); /* idle (again, if reaped) */
            ctx_put(c->ctx);
        }
        c->ctx = NULL;
    } else if (c->tcb) {
        dl_deallocate_tls(c->tcb, true);
    }
    c->tcb = NULL;
}

int cg_spawn(void *target, uint64_t serial, size_t stack_size, int cgroup_fd,
             int flags, struct cg_child **out)
{
    if (!g_started)
        return -ESRCH;
    size_t page = (size_t)sysconf(_SC_PAGESIZE);
    stack_size = (stack_size + page - 1) & ~(page - 1);
    if (stack_size < 16 * page)
        return -EINVAL;

    struct cg_child *c = calloc(1, sizeof *c);
    if (!c)
        return -ENOMEM;
    c->target = target;
    c->serial = serial;
    c->flags = flags;
    c->cgroup_fd = cgroup_fd;
    c->pidfd = -1;
    c->stack_size = stack_size;
    c->map_len = stack_size + page;      /* + a PROT_NONE guard below */
    c->map = mmap(NULL, c->map_len, PROT_READ | PROT_WRITE,
                  MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE | MAP_STACK,
                  -1, 0);
    if (c->map == MAP_FAILED) {
        free(c);
        return -ENOMEM;
    }
    mprotect(c->map, page, PROT_NONE);
    c->alt_len = 64 * 1024 + page;       /* + a guard page below */
    c->alt = mmap(NULL, c->alt_len, PROT_READ | PROT_WRITE,
                  MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE | MAP_STACK, -1, 0);
    if (c->alt == MAP_FAILED) {
        munmap(c->map, c->map_len);
        free(c);
        return -ENOMEM;
    }
    mprotect(c->alt, page, PROT_NONE);
    c->arena = -1;
    if (G.activate) {
        c->ctx = ctx_take();
        c->tcb = c->ctx ? c->ctx->tcb : NULL;
        if (c->tcb) {
            tls_reset(c->tcb);
            G.slot_bind(c->ctx->slot);
        }
    } else {
        c->tcb = tls_new();
    }
    c->tstate = c->tcb ? cg_tstate_new() : NULL;
    if (!c->tstate) {
        tls_give_back(c);
        munmap(c->alt, c->alt_len);
        munmap(c->map, c->map_len);
        free(c);
        return -ENOMEM;
    }
    struct cg_cmd cmd = {CMD_SPAWN, c, 0, 0};
    int r = submit(&cmd);
    if (r < 0) {
        forget_thread_state(c->tstate);
        tls_give_back(c);
        munmap(c->alt, c->alt_len);
        munmap(c->map, c->map_len);
        free(c);
        return r;
    }
    *out = c;
    return 0;
}

/* Set the child's stop flag; 1 if this call set it. */
int cg_request_stop(struct cg_child *c)
{
    int none = CG_STOP_NONE;
    if (!__atomic_compare_exchange_n(&c->stop_requested, &none, CG_STOP_PARENT,
                                     false, __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST))
        return 0;
    uint64_t one = 1;
    if (write(g_wakefd, &one, sizeof one) < 0) { /* counter cannot overflow */ }
    return 1;
}

/* Unlink and free a reaped child's PyThreadState (it was never current
   anywhere else).  A child killed inside Python leaves its tstate->cframe
   pointing into its stack: once that stack is unmapped, sys._current_frames()
   would crash, so this comes first.  Objects its frames referenced leak.  If
   the child died holding the GIL, the monitor released it before the death
   was reported: with gil_repair off this blocks forever. */
static void forget_thread_state(PyThreadState *t)
{
    PyGILState_STATE g = PyGILState_Ensure();
    PyThreadState_Clear(t);
    PyThreadState_Delete(t);
    PyGILState_Release(g);
}

/* Free what a reaped child had: -EBUSY if it is not reaped yet. */
int cg_release(struct cg_child *c)
{
    if (__atomic_load_n(&c->state, __ATOMIC_ACQUIRE) != CG_REAPED)
        return -EBUSY;
    forget_thread_state(c->tstate);
    munmap(c->map, c->map_len);
    munmap(c->alt, c->alt_len);
    tls_give_back(c);
    close(c->pidfd);
    free(c);
    return 0;
}

/* A reaped child whose Python state must stay where it is (the host keeps a
   crashed node's objects: destroying them could block on a lock the child
   held): its thread state and stacks stay allocated (its frames point into
   them); its TLS context goes back to the pool (or stays quarantined) and
   its pidfd is closed.  -EBUSY if not reaped yet. */
int cg_abandon(struct cg_child *c)
{
    if (__atomic_load_n(&c->state, __ATOMIC_ACQUIRE) != CG_REAPED)
        return -EBUSY;
    if (c->ctx)
        tls_give_back(c);
    if (c->pidfd >= 0)
        close(c->pidfd);
    c->pidfd = -1;
    return 0;
}
