/*
 * monitor.c - the monitor thread: one per core (cg_start), the only thread
 * that performs clone3 (PR_SET_PDEATHSIG fires when the *spawning thread*
 * dies, so children die with the monitor, i.e. with the container).  It
 * waits on the children's pidfds with epoll, and after a death calls
 * gilrepair.c to undo what the dead task left in CPython's GIL; then it
 * words the death and hands its CRASHED event to the herald thread if the
 * node is armed (herald.c), reports to Python through a pipe of fixed-size
 * records (struct cg_event) and leaves the zombie for cg_release to reap.  Between events, and
 * after each, it runs the lock doctor (mutexes.c) and the memory watch (memwatch.c), which say how
 * long it may sleep.  With --core-dumps it also has crashing children dumped (dumps.c).  It never
 * takes the GIL.  It alone touches the child list (g_children) and cg_child.stop_reported.
 * It runs real-time where the container may (monitor_realtime, below).
 *
 * Other threads talk to it through commands (spawn, stop) written as
 * pointers to a pipe, and through an eventfd that says "a stop flag was set"
 * (monitor_wake, from any thread or signal handler).
 */
#include "core.h"
#include "monitor.h"
#include "child.h"
#include "clonecore.h"
#include "contexts.h"
#include "deathtext.h"
#include "dumps.h"
#include "herald.h"
#include "memwatch.h"
#include "mutexes.h"

#include <errno.h>
#include <fcntl.h>
#include <linux/futex.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <string.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

static int g_epfd = -1, g_wakefd = -1, g_cmd[2] = {-1, -1}, g_ev[2] = {-1, -1};
static pthread_t g_monitor;
static struct cg_child *g_children; /* monitor-only */
static char TAG_CMD, TAG_WAKE;      /* epoll tags that are not children */
static int g_realtime_err = ENOSYS; /* cg_monitor_realtime's answer */

enum { CMD_SPAWN = 1, CMD_STOP = 2 };
struct cg_cmd { /* lives on the caller's stack */
    int op;
    struct cg_child *child;
    int result;
    uint32_t done; /* futex word */
};

static void cmd_finish(struct cg_cmd *cmd, int result)
{
    cmd->result = result;
    __atomic_store_n(&cmd->done, 1, __ATOMIC_RELEASE);
    /* The caller may already have returned; a wake on a stale address is a
       harmless spurious wake-up. */
    syscall(SYS_futex, &cmd->done, FUTEX_WAKE_PRIVATE, 1, NULL, NULL, 0);
}

static int submit(struct cg_cmd *cmd) /* from any thread; blocks */
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

/* One record onto the event pipe; blocks if Python lags >1000 records
   behind. */
void monitor_emit(const struct cg_event *ev)
{
    const char *p = (const char *)ev;
    size_t left = sizeof *ev;
    while (left) {
        ssize_t n = write(g_ev[1], p, left);
        if (n < 0 && errno == EINTR)
            continue;
        if (n < 0)
            return;
        p += n, left -= (size_t)n;
    }
}

int monitor_watch(int fd, void *tag)
{
    struct epoll_event ev = {.events = EPOLLIN, .data.ptr = tag};
    return epoll_ctl(g_epfd, EPOLL_CTL_ADD, fd, &ev) < 0 ? -errno : 0;
}

void monitor_unwatch(int fd)
{
    epoll_ctl(g_epfd, EPOLL_CTL_DEL, fd, NULL);
}

/* The record's alloc word for child c (CG_ALLOC_*, its slot). */
static uint32_t alloc_word(const struct cg_child *c)
{
    if (!c || !c->ctx)
        return 0;
    return ((uint32_t)c->ctx->slot & CG_ALLOC_SLOT_MASK) | (uint32_t)c->retired << CG_ALLOC_SHIFT;
}

static void emit(uint32_t kind, const struct cg_child *c, int status, int code, int64_t t,
                 uint32_t repairs, uint32_t flags)
{
    struct cg_event ev = {.kind = kind,
                          .pid = c ? c->pid : 0,
                          .status = status,
                          .code = code,
                          .serial = c ? c->serial : 0,
                          .t_ns = t,
                          .repairs = repairs,
                          .alloc = alloc_word(c),
                          .flags = flags};
    monitor_emit(&ev);
}

static void report_stop(struct cg_child *c, int64_t t)
{
    int s = __atomic_load_n(&c->stop_requested, __ATOMIC_ACQUIRE);
    if (s != CG_STOP_NONE && !c->stop_reported) {
        c->stop_reported = 1;
        emit(CG_EV_STOP, c, s, __atomic_load_n(&c->stop_signal, __ATOMIC_ACQUIRE), t, 0, 0);
    }
}

static int do_spawn(struct cg_child *c)
{
    c->start_ns = cg_mono_ns();
    long pid = child_clone(c);
    if (pid < 0)
        return (int)pid;
    c->pid = (int)pid;

    struct epoll_event ev = {.events = EPOLLIN, .data.ptr = c};
    if (epoll_ctl(g_epfd, EPOLL_CTL_ADD, c->pidfd, &ev) < 0) {
        int err = errno; /* cannot watch it: do not let it run */
        siginfo_t si;
        syscall(SYS_pidfd_send_signal, c->pidfd, SIGKILL, NULL, 0);
        waitid((idtype_t)P_PIDFD, (id_t)c->pidfd, &si, WEXITED | __WALL);
        close(c->pidfd);
        return -err;
    }
    c->next = g_children;
    g_children = c;
    mutexes_see(c); /* its main task, for a death before the
                       first periodic look (mutexes.c) */
    return 0;
}

/* Dead but not yet reaped (or reaped by someone else): its tid cannot have
   been reused. */
static bool child_is_dead(struct cg_child *c)
{
    siginfo_t si;
    memset(&si, 0, sizeof si);
    if (waitid((idtype_t)P_PIDFD, (id_t)c->pidfd, &si, WEXITED | __WALL | WNOHANG | WNOWAIT) < 0)
        return errno == ECHILD;
    return si.si_pid != 0;
}

/* What the repair (gilrepair.c) knows of child c's main task. */
static struct cg_dead as_dead(const struct cg_child *c)
{
    return (struct cg_dead){.pid = c->pid,
                            .tcb = c->tcb,
                            .stack_lo = c->map,
                            .stack_hi = c->map + c->map_len,
                            .slot = c->ctx ? c->ctx->slot : 0,
                            .ref_dropped = c->gil_ref_dropped};
}

static struct cg_repair_cfg repair_cfg(void)
{
    return (struct cg_repair_cfg){cg_cfg()->gil_repair, cg_cfg()->condvar_repair,
                                  cg_cfg()->interp_repair, cg_tcb_layout()->cleanup,
                                  (uintptr_t)cg_tcb_layout()->cond_cleanup};
}

void repair_step_aside(struct cg_child *c)
{
    /* Only the main task is described (tcb, stack); another crashing
       task leaves it running, free to end its wait itself.  A request
       taken after the asker's death (dumps_forget empties the pipe after
       the repair) is the repair's: it dropped the reference already, and
       a waiter it could not cancel still looks registered. */
    if (c->crash_tid != c->pid || c->repair_done)
        return;
    struct cg_dead d = as_dead(c);
    struct cg_repair_cfg cfg = repair_cfg();
    c->gil_ref_dropped = cg_gil_step_aside(&d, &cfg);
}

/* Undo what dead children left in the GIL (gilrepair.c): every dead child
   not looked at yet, so that one repair never waits for a lock or a
   condvar reference another dead child holds. */
static void repair_after_death(struct cg_child *reaped)
{
    if (!cg_cfg()->gil_repair && !cg_cfg()->condvar_repair)
        return;
    struct cg_dead d[32];
    struct cg_child *who[32];
    int n = 0;
    for (struct cg_child *c = g_children; c && n < 32; c = c->next)
        if (!c->repair_done && (c == reaped || child_is_dead(c))) {
            d[n] = as_dead(c);
            who[n++] = c;
        }
    struct cg_repair_cfg cfg = repair_cfg();
    uint32_t misc = cg_gil_repair(d, n, &cfg);
    for (int i = 0; i < n; i++) {
        who[i]->repairs |= d[i].repairs;
        who[i]->repair_done = 1;
        if (d[i].gil_code) {
            who[i]->gil_code = d[i].gil_code;
            who[i]->gil_lasti = d[i].gil_lasti;
        }
    }
    reaped->repairs |= misc;
}

/* It died of a fault of its own (a bad access, an abort, a trap), not of a
   signal another process sent: then what it last wrote may have torn its
   heap.  Its crash report (crash.c), once complete, names the sender;
   without one (none installed, or cut short), a fault signal counts as its
   own. */
static bool faulted_itself(const struct cg_child *c, int status, int code)
{
    if (code != CLD_KILLED && code != CLD_DUMPED)
        return false;
    switch (status) {
    case SIGSEGV:
    case SIGBUS:
    case SIGILL:
    case SIGFPE:
    case SIGABRT:
    case SIGTRAP:
    case SIGSYS:
        break;
    default:
        return false;
    }
    bool seen = __atomic_load_n(&c->crash_nframes, __ATOMIC_ACQUIRE) > 0;
    return !(seen && c->crash_si_code <= 0 && c->crash_sender != c->pid);
}

static void reap(struct cg_child *c, int64_t t)
{
    siginfo_t si;
    memset(&si, 0, sizeof si);
    /* WNOWAIT: look, repair, report; cg_release reaps (the pid stays ours). */
    int r = waitid((idtype_t)P_PIDFD, (id_t)c->pidfd, &si, WEXITED | __WALL | WNOHANG | WNOWAIT);
    if (r == 0 && si.si_pid == 0)
        return; /* readable but not yet waitable */
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
        c->retired = guard_retire(c->ctx, r == 0 && faulted_itself(c, status, code));
    /* Its words, and its CRASHED event out at once if the herald may say it
       (herald.c), before the rest of the bookkeeping. */
    uint32_t alloc = alloc_word(c);
    int asked = __atomic_load_n(&c->stop_requested, __ATOMIC_ACQUIRE);
    cg_describe_death(status, code, c->repairs, alloc,
                      asked == CG_STOP_SIGNAL ? __atomic_load_n(&c->stop_signal, __ATOMIC_ACQUIRE)
                                              : 0,
                      c->death_text, CG_DEATH_TEXT);
    if (alloc & CG_ALLOC_OVER_BUDGET)
        guard_say_over_budget(c->ctx, c->death_text, CG_DEATH_TEXT);
    memwatch_say(c, c->death_text, CG_DEATH_TEXT);
    uint32_t flags =
        herald_claim(c, status, code, alloc & CG_ALLOC_QUARANTINED) ? CG_EVF_CLAIMED : 0;
    if (c->oom_in_use)
        flags |= CG_EVF_OUT_OF_MEMORY;
    /* Left a zombie (its pid still ours) for Python's release to reap
       (clonecore.c): the reaping waitid took ~0.9 ms of kernel time with 48
       node processes (median, bench.crash_latency --others 47), on the CPU
       the death's report needs next. */
    report_stop(c, t); /* never after the death record */
    mutexes_bury(c);   /* its tasks may prove a mutex's owner dead */
    if (cg_cfg()->core_dumps)
        dumps_forget(c); /* Python may release it once told */
    epoll_ctl(g_epfd, EPOLL_CTL_DEL, c->pidfd, NULL);
    for (struct cg_child **p = &g_children; *p; p = &(*p)->next)
        if (*p == c) {
            *p = c->next;
            break;
        }
    __atomic_store_n(&c->state, CG_REAPED, __ATOMIC_RELEASE);
    emit(CG_EV_DEATH, c, status, code, t, c->repairs, flags);
}

/* How long the monitor may sleep now: the lock doctor, dumps and the
   memory watch each say. */
static int next_look(int64_t t)
{
    return memwatch_tick(g_children, dumps_tick(t, mutexes_tick(g_children, t)));
}

static void *monitor_main(void *unused)
{
    (void)unused;
    struct epoll_event evs[32];
    int sleep_ms = -1;
    for (;;) {
        int n = epoll_wait(g_epfd, evs, 32, sleep_ms);
        int64_t t = cg_mono_ns();
        if (n <= 0) { /* EINTR (all signals are blocked),
                         or time for the lock doctor */
            sleep_ms = next_look(t);
            continue;
        }
        /* Commands, stop notices and dumps first, deaths second: a stop
           notice of a child must reach Python before its death record. */
        for (int i = 0; i < n; i++) {
            if (cg_cfg()->core_dumps && dumps_event(evs[i].data.ptr, t)) {
                evs[i].data.ptr = NULL; /* handled: not a child */
            } else if (evs[i].data.ptr == &TAG_WAKE) {
                uint64_t v;
                if (read(g_wakefd, &v, sizeof v) < 0) { /* EAGAIN */
                }
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
                        emit(CG_EV_CLOSED, NULL, 0, 0, t, 0, 0);
                        cmd_finish(cmd, 0);
                        return NULL;
                    }
                }
            }
        }
        for (int i = 0; i < n; i++)
            if (evs[i].data.ptr && evs[i].data.ptr != &TAG_WAKE && evs[i].data.ptr != &TAG_CMD)
                reap(evs[i].data.ptr, t);
        sleep_ms = next_look(cg_mono_ns());
    }
}

static void close_fds(void)
{
    int *fds[] = {&g_epfd, &g_wakefd, &g_cmd[0], &g_cmd[1], &g_ev[1]};
    for (size_t i = 0; i < sizeof fds / sizeof fds[0]; i++)
        if (*fds[i] >= 0)
            close(*fds[i]), *fds[i] = -1;
}

/* The monitor at the lowest real-time priority (SCHED_FIFO 1) where the
   container may (root, CAP_SYS_NICE, or an RLIMIT_RTPRIO of 1): nodes that
   keep the CPUs busy cannot delay its looks.  The memory watch must win its
   race against a leak within the margin's time, and an ordinary monitor
   thread under a full load was seen 24 MiB late of a 64 MiB margin, and once
   past it (the kernel's OOM killer then ended the container).  What it does
   is short and never waits for a lower-priority thread by spinning: epoll,
   reaping, /proc and cgroup reads, clone3; dumps are written by a gcore it
   spawns.  SCHED_RESET_ON_FORK: the node processes it clones and the helpers
   it spawns get the ordinary policy.  0, or the errno that refused it. */
static int monitor_realtime(void)
{
    struct sched_param p = {.sched_priority = sched_get_priority_min(SCHED_FIFO)};
    return pthread_setschedparam(g_monitor, SCHED_FIFO | SCHED_RESET_ON_FORK, &p);
}

int cg_monitor_realtime(void)
{
    return g_realtime_err;
}

/* Start the monitor.  *event_fd receives the read end of the event pipe,
   which Python owns (and closes after cg_stop). */
int monitor_start(int *event_fd)
{
    int r = mutexes_start();
    if (r < 0)
        return r;
    g_epfd = epoll_create1(EPOLL_CLOEXEC);
    g_wakefd = eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
    if (g_epfd < 0 || g_wakefd < 0 || pipe2(g_cmd, O_CLOEXEC) < 0 || pipe2(g_ev, O_CLOEXEC) < 0) {
        int err = errno;
        close_fds();
        return -err;
    }
    struct epoll_event e1 = {.events = EPOLLIN, .data.ptr = &TAG_CMD};
    struct epoll_event e2 = {.events = EPOLLIN, .data.ptr = &TAG_WAKE};
    epoll_ctl(g_epfd, EPOLL_CTL_ADD, g_cmd[0], &e1);
    epoll_ctl(g_epfd, EPOLL_CTL_ADD, g_wakefd, &e2);
    if ((r = dumps_start()) < 0) {
        dumps_stop();
        close(g_ev[0]);
        g_ev[0] = -1;
        close_fds();
        return r;
    }

    /* The monitor runs with every signal blocked (process-directed signals
       go to other threads); children inherit that mask and clear it.  All
       but the ones a fault raises: blocked, a fault of its own kills the
       container silently (the kernel delivers it anyway, default action,
       no handler run); unblocked, the container's crash report names it. */
    sigset_t all, old;
    sigfillset(&all);
    static const int faults[] = {SIGSEGV, SIGBUS, SIGILL, SIGFPE, SIGABRT, SIGTRAP};
    for (size_t i = 0; i < sizeof faults / sizeof faults[0]; i++)
        sigdelset(&all, faults[i]);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    int err = pthread_create(&g_monitor, NULL, monitor_main, NULL);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (!err) {
        pthread_setname_np(g_monitor, "cg-monitor"); /* for ps, gdb, benchmarks */
        g_realtime_err = monitor_realtime();
    }
    if (err) {
        dumps_stop();
        close(g_ev[0]);
        g_ev[0] = -1;
        close_fds();
        return -err;
    }
    *event_fd = g_ev[0];
    g_ev[0] = -1;
    return 0;
}

/* Stop the monitor: -EBUSY while any child is unreaped. */
int monitor_stop(void)
{
    struct cg_cmd cmd = {CMD_STOP, NULL, 0, 0};
    int r = submit(&cmd);
    if (r != 0)
        return r;
    pthread_join(g_monitor, NULL);
    dumps_stop();
    close_fds();
    return 0;
}

/* Have the monitor clone3 the child (from any thread; blocks until done). */
int monitor_spawn(struct cg_child *c)
{
    struct cg_cmd cmd = {CMD_SPAWN, c, 0, 0};
    return submit(&cmd);
}

/* A stop flag was set: the monitor reports it.  An eventfd write is
   async-signal-safe; the counter cannot overflow in practice. */
void monitor_wake(void)
{
    uint64_t one = 1;
    if (write(g_wakefd, &one, sizeof one) < 0) { /* nothing to do */
    }
}
