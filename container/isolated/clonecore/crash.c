/*
 * crash.c - a child's crash report: on SIGSEGV, SIGBUS, SIGILL, SIGFPE or
 * SIGABRT, a report on fd 2 (the signal, the address, the Python and native
 * stacks), then the same death as without it.  Installed by the child
 * itself (child_main); runs in the crashing task, on memory the container
 * shares, so it stays small and async-signal-safe but for the calls named
 * at on_crash.
 *
 * The child writes only the report's head.  Its stacks it records raw in
 * its control block, and the container writes them after it has reported
 * the death (crash_reports.py): the native frames' addresses
 * (cg_child.crash_frames; one address space, so they mean the same there),
 * symbolized with cg_write_native_stack, and each Python frame's code
 * object and instruction offset (crash_py_code, crash_py_lasti), written
 * with cg_write_py_stack.  Symbolizing (dladdr, one linear scan of a
 * library's symbols per frame) took ~0.5 ms of the ~0.65 ms a report took,
 * and writing the Python stack (a few small write()s a frame) ~0.23 ms at
 * 25 frames, all of it before the death could be reported.  A thread the
 * child created has no control block of its own: it writes its report
 * whole, in place.
 *
 * The container itself installs the same report for its own threads
 * (cg_container_crash_report, isolated mode): on a fatal signal in the
 * container, its native stack and the faulting thread's Python stack, then
 * the handler that was there before (faulthandler's: every thread's Python
 * stack) runs, and the process dies as it would have.
 */
#include "core.h"
#include "crash.h"
#include "clonecore.h"
#include "dumps.h"
#include "sigsafe.h"

#include <errno.h>
#include <linux/futex.h>
#include <execinfo.h>
#include <signal.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <ucontext.h>
#include <unistd.h>

/* The signal a crash report is about (for its watchdog, on the same thread).
   initial-exec: a plain %fs-relative access, no __tls_get_addr. */
static __thread int cg_crash_sig __attribute__((tls_model("initial-exec")));
/* The child whose main task this is (NULL in threads the child created). */
static __thread struct cg_child *cg_crashing __attribute__((tls_model("initial-exec")));
static pid_t g_container_pid;

static const int crash_signals[] = {SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGABRT};
#define NCRASH ((int)(sizeof crash_signals / sizeof crash_signals[0]))

/* The container's own report: the handlers it replaced (faulthandler's), in
   crash_signals order; set once, before any fault can use them. */
static struct sigaction g_container_prev[NCRASH];
static int g_container_installed;

/* The report did not finish within 2 s (the symboliser waits for the
   dynamic linker's lock, say): die of the signal we were reporting.  It is
   SIG_DFL again (SA_RESETHAND) and blocked while its handler runs. */
static void on_crash_timeout(int unused)
{
    (void)unused;
    int sig = cg_crash_sig;
    if (g_container_installed && getpid() == g_container_pid)
        for (int i = 0; i < NCRASH; i++) /* no SA_RESETHAND there: the old one */
            if (crash_signals[i] == sig)
                sigaction(sig, &g_container_prev[i], NULL);
    sigset_t s;
    sigemptyset(&s);
    sigaddset(&s, sig);
    syscall(SYS_tgkill, getpid(), syscall(SYS_gettid), sig);
    sigprocmask(SIG_UNBLOCK, &s, NULL);
}

/* --core-dumps: ask the monitor for a dump of this process (dumps.c) and
   wait here, the fault's state intact, until it is written or
   CG_CORE_WAIT_S have passed.  The report's watchdog is off meanwhile: gdb
   takes seconds over a large address space. */
static void wait_for_dump(struct cg_child *c, bool timer_ok, int timer)
{
    if (timer_ok) {
        struct itimerspec off = {{0, 0}, {0, 0}};
        syscall(SYS_timer_settime, timer, 0, &off, NULL);
    }
    __atomic_store_n(&c->core_dump, CG_CORE_ASKED, __ATOMIC_RELEASE);
    if (!dumps_ask(c)) {
        __atomic_store_n(&c->core_dump, CG_CORE_FAILED, __ATOMIC_RELEASE);
        return;
    }
    struct timespec slice = {1, 0};
    for (int waited = 0; waited < CG_CORE_WAIT_S &&
                         __atomic_load_n(&c->core_dump, __ATOMIC_ACQUIRE) == CG_CORE_ASKED;
         waited++)
        syscall(SYS_futex, &c->core_dump, FUTEX_WAIT_PRIVATE, CG_CORE_ASKED, &slice, NULL, 0);
}

/* One report on fd 2, then the same death as without us: the handler was
   installed SA_RESETHAND, so the disposition is SIG_DFL again, and the
   signal is re-sent to this thread; it is delivered (and kills the child)
   as the handler returns.  A fault inside here kills at once (SIG_DFL).
   Everything used is async-signal-safe, except backtrace (its unwinder was
   loaded by cg_start; on glibc 2.35+ it finds FDEs without locks), the
   Python stack dump (faulthandler's, lock-free) and, in a thread the child
   created, backtrace_symbols_fd (dladdr, which takes the loader's lock:
   hence the watchdog timer). */
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
    sev._sigev_un._tid = tid; /* sigev_notify_thread_id */
    int timer;
    bool timer_ok = syscall(SYS_timer_create, CLOCK_MONOTONIC, &sev, &timer) == 0;
    if (timer_ok) {
        struct itimerspec its = {{0, 0}, {2, 0}};
        syscall(SYS_timer_settime, timer, 0, &its, NULL);
    }

    char text[256];
    struct ss_buf o = SS_BUF(text);
    const char *abbrev = sigabbrev_np(sig);
    bool container = g_container_installed && pid == g_container_pid;
    ss_str(&o, container ? "cloneguard: container pid " : "cloneguard: pid ");
    ss_dec(&o, (long)pid);
    ss_str(&o, " caught SIG");
    ss_str(&o, abbrev ? abbrev : "?");
    ss_str(&o, " at ");
    if (si->si_code > 0) /* raised by a fault */
        ss_hex(&o, (uintptr_t)si->si_addr);
    else /* sent: there is no address */
        ss_str(&o, "-");
    ss_str(&o, " (pc ");
    ss_hex(&o, (unsigned long)uc->uc_mcontext.gregs[REG_RIP]);
    ss_str(&o, ")\ncloneguard: si_code ");
    ss_dec(&o, si->si_code);
    if (si->si_code <= 0) {
        ss_str(&o, " (sent by pid ");
        ss_dec(&o, (long)si->si_pid);
        ss_str(&o, ")");
    }
    if (sig == SIGSEGV && si->si_code == SEGV_PKUERR) {
        /* A write the PKRU forbids: into a heap under another node's key
           (allocguard.c, heapkeys.c). */
        ss_str(&o, " (protection-key violation, key ");
        ss_dec(&o, (long)si->si_pkey);
        ss_str(&o, ")");
    }
    if (tid != pid) {
        ss_str(&o, ", thread ");
        ss_dec(&o, (long)tid);
    }
    ss_str(&o, "\n");
    struct cg_child *c = cg_crashing;
    int unclaimed = 0;
    bool claimed = c && __atomic_compare_exchange_n(&c->crash_nframes, &unclaimed, -1, false,
                                                    __ATOMIC_ACQ_REL, __ATOMIC_ACQUIRE);
    if (claimed) {
        /* The fault, and both stacks, raw: the container writes them once
           it has reported the death. */
        ss_flush(&o, 2);
        c->crash_tid = tid;
        c->crash_si_code = si->si_code;
        c->crash_sender = si->si_code <= 0 ? (int)si->si_pid : 0;
        c->crash_addr = si->si_code > 0 ? si->si_addr : NULL;
        c->crash_pkey = sig == SIGSEGV && si->si_code == SEGV_PKUERR ? (int)si->si_pkey : 0;
        c->crash_py_nframes = cg_record_py_stack(c->crash_py_code, c->crash_py_lasti,
                                                 CG_CRASH_PY_FRAMES, &c->crash_py_more);
        int n = backtrace(c->crash_frames, CG_CRASH_FRAMES);
        __atomic_store_n(&c->crash_nframes, n > 0 ? n : 0, __ATOMIC_RELEASE);
    } else {
        void *frames[CG_CRASH_FRAMES];
        ss_str(&o, "cloneguard: native stack:\n");
        ss_flush(&o, 2);
        int n = backtrace(frames, CG_CRASH_FRAMES);
        backtrace_symbols_fd(frames, n, 2);
        ss_str(&o, "cloneguard: Python ");
        ss_flush(&o, 2);
        cg_dump_py_stack(2); /* "Stack (most recent call first): ..." */
    }

    if (claimed && cg_cfg()->core_dumps)
        wait_for_dump(c, timer_ok, timer);
    if (container) {
        /* Then whoever handled it before us: faulthandler dumps every
           thread and re-raises.  The signal is blocked until we return. */
        for (int i = 0; i < NCRASH; i++)
            if (crash_signals[i] == sig)
                sigaction(sig, &g_container_prev[i], NULL);
        struct itimerspec off = {{0, 0}, {0, 0}};
        if (timer_ok)
            syscall(SYS_timer_settime, timer, 0, &off, NULL);
    }
    syscall(SYS_tgkill, pid, tid, sig);
    errno = saved;
}

void crash_handlers_install(struct cg_child *c)
{
    cg_crashing = c;
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
    for (int i = 0; i < NCRASH; i++)
        sigaction(crash_signals[i], &sa, NULL);
}

/* In the container (isolated mode), after faulthandler.enable(): the same
   report for a fatal signal in any of its own threads, then the handler it
   replaces.  Needs no signal stack of its own: faulthandler's alternate
   stack serves (it sets one up for the calling thread). 0, or -errno. */
int cg_container_crash_report(void)
{
    g_container_pid = getpid();
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_sigaction = on_crash;
    sa.sa_flags = SA_SIGINFO | SA_ONSTACK;
    sigemptyset(&sa.sa_mask);
    for (int i = 0; i < NCRASH; i++)
        if (sigaction(crash_signals[i], &sa, &g_container_prev[i]) < 0)
            return -errno;
    g_container_installed = 1;
    return 0;
}

void crash_report_prepare(void)
{
    /* The first backtrace() dlopens libgcc_s: never in a handler. */
    void *warm[4];
    backtrace(warm, 4);
}

/* In the container, after the death was reported: a crashed child's native
   frames (cg_child.crash_frames), one line each, as backtrace_symbols_fd
   writes them.  dladdr takes the loader's lock: Python calls this from a
   thread of its own, never from one the container needs. */
void cg_write_native_stack(void *const *frames, int n, int fd)
{
    backtrace_symbols_fd(frames, n, fd);
}
