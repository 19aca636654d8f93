/*
 * dumps.c - --core-dumps, on the monitor thread: the dump of a child whose
 * main task caught a fatal signal, written while that task waits in its
 * crash handler (crash.c), with no Python involved.
 *
 * The crashing task writes its control block's address to the request pipe
 * (dumps_ask, async-signal-safe) and waits on cg_child.core_dump.  The
 * monitor, one dump at a time, runs gdb's gcore on it (a process of its own,
 * posix_spawn'ed, watched through its pidfd in the monitor's epoll like the
 * children are), then `fallocate --dig-holes` on the file, and then sets
 * core_dump to CG_CORE_DONE or CG_CORE_FAILED (core_why says why) and wakes
 * the task, which goes on to die; Python reads the outcome from the block
 * with the death.  Nothing on that path takes a lock a child may hold: no
 * GIL, no Python lock, no malloc (the spawn's file actions and attributes
 * are made at start-up), so a task that crashed holding any of them is
 * dumped all the same (if it holds the GIL, the container's Python threads
 * wait for the dump with it; if it only waited for the GIL, it steps aside
 * as its request is taken: take_requests).
 *
 * The watch clock (cg_watch_clock_ns), which the container's watchdog reads,
 * stands still from a request to the end of the last dump queued.
 *
 * While gdb writes, the allocator guard's reserved and never-used address
 * space is MADV_DONTDUMP (guard_dump_exclude): gdb writes every
 * readable page, and that space is tens of GiB of zeros.
 *
 * The block stays valid while the monitor uses it: a child's block is
 * released only after its death record, which the monitor writes after
 * dumps_forget, on this same thread.
 */
#include "core.h"
#include "dumps.h"
#include "clonecore.h"
#include "contexts.h"
#include "monitor.h"
#include "sigsafe.h"

#include <errno.h>
#include <fcntl.h>
#include <linux/futex.h>
#include <signal.h>
#include <spawn.h>
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <unistd.h>

#define HELPER_S 300 /* gdb, or fallocate, may take this long */
#define STR(x) STR_(x)
#define STR_(x) #x

enum { IDLE, GCORE, HOLES };

static int g_req[2] = {-1, -1}; /* requests: cg_child pointers */
static int g_log = -1;          /* memfd: the helpers' output */
static posix_spawn_file_actions_t g_actions;
static posix_spawnattr_t g_attr;
static bool g_ready;
static char TAG_REQ, TAG_HELPER;

/* The dump under way (monitor-only). */
static int g_stage = IDLE;
static struct cg_child *g_child; /* NULL once it died meanwhile */
static struct cg_child *g_queue; /* waiting, oldest first (dump_next) */
static int g_helper_fd = -1;     /* the helper's pidfd */
static int64_t g_deadline;
static bool g_timed_out;
static char g_path[CG_CORE_PATH];

/* The watch clock (cg_watch_clock_ns): CLOCK_MONOTONIC less the time the
   monitor had a dump asked for or under way.  While a node that crashed
   holding the GIL waits for its dump, no Python runs: the container's
   watchdog (lastresort.c, container/watchdog.py) reads this clock so that
   it does not take that for a hang.  Written here only, on the monitor
   thread; read from any thread: the sequence count (odd while the two
   words change) makes them one reading. */
static unsigned g_pause_seq;
static int64_t g_paused_ns;   /* in dumps that are over */
static int64_t g_pause_since; /* 0: no dump asked for or under way */

static void note_busy(int64_t now)
{
    bool busy = g_stage != IDLE || g_queue != NULL;
    if (busy == (g_pause_since != 0))
        return;
    __atomic_store_n(&g_pause_seq, g_pause_seq + 1, __ATOMIC_RELAXED);
    __atomic_thread_fence(__ATOMIC_RELEASE);
    if (busy) {
        __atomic_store_n(&g_pause_since, now, __ATOMIC_RELAXED);
    } else {
        __atomic_store_n(&g_paused_ns, g_paused_ns + (now - g_pause_since), __ATOMIC_RELAXED);
        __atomic_store_n(&g_pause_since, 0, __ATOMIC_RELAXED);
    }
    __atomic_store_n(&g_pause_seq, g_pause_seq + 1, __ATOMIC_RELEASE);
}

int64_t cg_watch_clock_ns(void)
{
    for (;;) {
        unsigned seq = __atomic_load_n(&g_pause_seq, __ATOMIC_ACQUIRE);
        int64_t paused = __atomic_load_n(&g_paused_ns, __ATOMIC_RELAXED);
        int64_t since = __atomic_load_n(&g_pause_since, __ATOMIC_RELAXED);
        __atomic_thread_fence(__ATOMIC_ACQUIRE);
        if ((seq & 1) == 0 && __atomic_load_n(&g_pause_seq, __ATOMIC_RELAXED) == seq)
            return (since ? since : cg_mono_ns()) - paused;
    }
}

/* What the helpers run with: nothing of the container's environment. */
static char *const HELPER_ENV[] = {"PATH=/usr/bin:/bin", "LC_ALL=C", NULL};

int dumps_start(void)
{
    if (!cg_cfg()->core_dumps)
        return 0;
    if (pipe2(g_req, O_CLOEXEC) < 0 || fcntl(g_req[0], F_SETFL, O_NONBLOCK) < 0)
        return -errno;
    g_log = memfd_create("cloneguard-dump-log", MFD_CLOEXEC);
    if (g_log < 0)
        return -errno;
    int r = posix_spawn_file_actions_init(&g_actions);
    if (r)
        return -r;
    if ((r = posix_spawnattr_init(&g_attr))) {
        posix_spawn_file_actions_destroy(&g_actions);
        return -r;
    }
    g_ready = true; /* dumps_stop destroys them */
    /* stdin from /dev/null; stdout and stderr into the log. */
    r = posix_spawn_file_actions_addopen(&g_actions, 0, "/dev/null", O_RDONLY, 0);
    if (!r)
        r = posix_spawn_file_actions_adddup2(&g_actions, g_log, 1);
    if (!r)
        r = posix_spawn_file_actions_adddup2(&g_actions, g_log, 2);
    /* The monitor blocks every signal; the helper must not. */
    sigset_t none, all;
    sigemptyset(&none);
    sigfillset(&all);
    if (!r)
        r = posix_spawnattr_setsigmask(&g_attr, &none);
    if (!r)
        r = posix_spawnattr_setsigdefault(&g_attr, &all);
    if (!r)
        r = posix_spawnattr_setflags(&g_attr, POSIX_SPAWN_SETSIGMASK | POSIX_SPAWN_SETSIGDEF);
    if (r)
        return -r;
    return monitor_watch(g_req[0], &TAG_REQ);
}

/* From a crashing child's handler: one pointer, atomic as any pipe write
   under PIPE_BUF.  False if it could not be asked. */
bool dumps_ask(struct cg_child *c)
{
    ssize_t n;
    do
        n = write(g_req[1], &c, sizeof c);
    while (n < 0 && errno == EINTR);
    return n == sizeof c;
}

static void say(struct cg_child *c, const char *a, const char *b)
{
    struct ss_buf o = SS_BUF(c->core_why);
    ss_str(&o, a);
    ss_str(&o, b);
    ss_cstr(&o);
}

/* The last line the helper printed ("" if none), but for gdb's own
   "[Inferior 1 (process N) detached]": gdb's error comes before it. */
static const char *last_line(void)
{
    static char tail[512];
    struct stat st;
    tail[0] = 0;
    if (fstat(g_log, &st) < 0 || st.st_size == 0)
        return tail;
    off_t from = st.st_size > (off_t)sizeof tail - 1 ? st.st_size - (off_t)sizeof tail + 1 : 0;
    ssize_t n = pread(g_log, tail, sizeof tail - 1, from);
    if (n < 0)
        n = 0;
    for (;;) {
        while (n > 0 && (tail[n - 1] == '\n' || tail[n - 1] == ' '))
            n--;
        tail[n] = 0;
        char *line = strrchr(tail, '\n');
        line = line ? line + 1 : tail;
        if (strncmp(line, "[Inferior ", 10) != 0 || line == tail)
            return line;
        n = line - tail;
    }
}

/* gdb wrote path: a regular file (start_next saw nothing there before). */
static bool written(const char *path)
{
    struct stat st;
    return lstat(path, &st) == 0 && S_ISREG(st.st_mode);
}

static int spawn_helper(char *const argv[], int64_t now)
{
    if (ftruncate(g_log, 0) < 0)
        return -errno;
    pid_t pid;
    int r = posix_spawn(&pid, argv[0], &g_actions, &g_attr, argv, HELPER_ENV);
    if (r)
        return -r;
    g_helper_fd = (int)syscall(SYS_pidfd_open, pid, 0);
    int err = g_helper_fd < 0 ? errno : -monitor_watch(g_helper_fd, &TAG_HELPER);
    if (err) { /* cannot watch it: end it now */
        kill(pid, SIGKILL);
        waitpid(pid, NULL, __WALL);
        if (g_helper_fd >= 0)
            close(g_helper_fd), g_helper_fd = -1;
        return -err;
    }
    g_deadline = now + (int64_t)HELPER_S * 1000000000;
    g_timed_out = false;
    return 0;
}

/* The child's dump is over: let its crash handler go on. */
static void finish(int outcome)
{
    struct cg_child *c = g_child;
    g_child = NULL;
    g_stage = IDLE;
    if (!c)
        return;
    __atomic_store_n(&c->core_dump, outcome, __ATOMIC_RELEASE);
    syscall(SYS_futex, &c->core_dump, FUTEX_WAKE_PRIVATE, 1, NULL, NULL, 0);
}

/* The path Python named, read twice: Python may be naming it again (once
   the node's name is known) at this very moment. */
static bool read_path(struct cg_child *c)
{
    for (int tries = 0; tries < 3; tries++) {
        memcpy(g_path, c->core_path, sizeof g_path);
        g_path[sizeof g_path - 1] = 0;
        if (memcmp(g_path, c->core_path, strlen(g_path) + 1) == 0)
            return g_path[0] != 0;
    }
    return false;
}

static void start_next(int64_t now)
{
    while (g_stage == IDLE && g_queue) {
        struct cg_child *c = g_queue;
        g_queue = c->dump_next;
        c->dump_next = NULL;
        g_child = c;
        struct stat st;
        if (!read_path(c)) {
            say(c, "no file was named for it", NULL);
            finish(CG_CORE_FAILED);
            continue;
        }
        if (lstat(g_path, &st) == 0) {                   /* not ours: never written over, */
            say(c, "something is in the way: ", g_path); /* taken or removed */
            finish(CG_CORE_FAILED);
            continue;
        }
        static char pid[16], gcore[CG_CORE_PATH + 8];
        snprintf(pid, sizeof pid, "%d", c->pid);
        snprintf(gcore, sizeof gcore, "gcore %s", g_path);
        /* execve's argv is char *const[] (for old callers' sake); it writes
           none of the strings, so the configuration's are passed as they are. */
        char *const argv[] = {
            (char *)cg_cfg()->gdb, "-nx", "-batch", "-p", pid, "-ex", gcore, NULL};
        guard_dump_exclude(1);
        int r = spawn_helper(argv, now);
        if (r < 0) {
            guard_dump_exclude(0);
            say(c, "gdb did not start: ", strerror(-r));
            finish(CG_CORE_FAILED);
            continue;
        }
        g_stage = GCORE;
    }
}

static void helper_ended(int64_t now)
{
    siginfo_t si;
    memset(&si, 0, sizeof si);
    /* ECHILD: something in the container reaped it first; the file says. */
    if (waitid((idtype_t)P_PIDFD, (id_t)g_helper_fd, &si, WEXITED | __WALL) < 0)
        si.si_code = 0;
    monitor_unwatch(g_helper_fd);
    close(g_helper_fd);
    g_helper_fd = -1;
    if (g_stage == GCORE) {
        guard_dump_exclude(0);
        struct cg_child *c = g_child;
        if (!c || g_timed_out) { /* what gdb left, if anything, is partial */
            unlink(g_path);
            if (c)
                say(c, "gdb took over " STR(HELPER_S) " s and was ended", NULL);
            finish(CG_CORE_FAILED);
        } else if (!written(g_path)) {
            const char *line = last_line();
            say(c, "gdb wrote none: ", line[0] ? line : "no output");
            finish(CG_CORE_FAILED);
        } else if (cg_cfg()->fallocate[0]) {
            char *const argv[] = {(char *)cg_cfg()->fallocate, "--dig-holes", g_path, NULL};
            if (spawn_helper(argv, now) == 0)
                g_stage = HOLES;
            else /* the file stays whole */
                finish(CG_CORE_DONE);
        } else {
            finish(CG_CORE_DONE);
        }
    } else {
        finish(CG_CORE_DONE); /* holes or none, the dump is whole */
    }
    start_next(now);
}

/* Every request written so far, onto the queue.  Each asker waits frozen
   in its crash handler until its dump is written, which may be seconds
   behind others': if it was waiting for the GIL, it stops holding up those
   who hand the GIL on (repair_step_aside). */
static void take_requests(void)
{
    struct cg_child *c;
    while (read(g_req[0], &c, sizeof c) == sizeof c && c) {
        repair_step_aside(c);
        struct cg_child **end = &g_queue;
        while (*end)
            end = &(*end)->dump_next;
        *end = c;
    }
}

/* An epoll event of ours: true if tag was one. */
bool dumps_event(void *tag, int64_t now)
{
    if (tag == &TAG_REQ) {
        take_requests();
        start_next(now);
        return true;
    }
    if (tag == &TAG_HELPER) {
        helper_ended(now);
        return true;
    }
    return false;
}

/* After each of the monitor's rounds: the next dump, if none is under way;
   how long the monitor may sleep for us (ms, -1: forever), given its own
   wish; a helper past its time is ended (its end comes through epoll). */
int dumps_tick(int64_t now, int sleep_ms)
{
    start_next(now); /* requests dumps_forget took off the pipe */
    note_busy(now);  /* every round ends here (monitor.c) */
    if (g_helper_fd < 0)
        return sleep_ms;
    if (now >= g_deadline) {
        if (!g_timed_out)
            syscall(SYS_pidfd_send_signal, g_helper_fd, SIGKILL, NULL, 0);
        g_timed_out = true;
        return sleep_ms;
    }
    int ms = (int)((g_deadline - now) / 1000000) + 1;
    return sleep_ms < 0 || ms < sleep_ms ? ms : sleep_ms;
}

/* Child c is dead and about to be reported: never touch it again. */
static void forget(struct cg_child *c)
{
    for (struct cg_child **p = &g_queue; *p; p = &(*p)->dump_next)
        if (*p == c) {
            *p = c->dump_next;
            say(c, "it died before its dump was begun", NULL);
            __atomic_store_n(&c->core_dump, CG_CORE_FAILED, __ATOMIC_RELEASE);
            return;
        }
    if (c != g_child)
        return;
    if (g_stage == HOLES) { /* the dump is written; only holes were left */
        __atomic_store_n(&c->core_dump, CG_CORE_DONE, __ATOMIC_RELEASE);
    } else {
        say(c, "it died while gdb was writing its dump", NULL);
        __atomic_store_n(&c->core_dump, CG_CORE_FAILED, __ATOMIC_RELEASE);
    }
    g_child = NULL;
}

void dumps_forget(struct cg_child *c)
{
    /* Its request may still be in the pipe (epoll need not have said so
       yet): take every one now, or c's would be read after c is freed. */
    take_requests(); /* the next dumps_tick starts them */
    forget(c);
}

/* The monitor stops (no child left): end a helper still running. */
void dumps_stop(void)
{
    if (g_helper_fd >= 0) {
        siginfo_t si;
        syscall(SYS_pidfd_send_signal, g_helper_fd, SIGKILL, NULL, 0);
        waitid((idtype_t)P_PIDFD, (id_t)g_helper_fd, &si, WEXITED | __WALL);
        close(g_helper_fd);
        g_helper_fd = -1;
        if (g_stage == GCORE)
            guard_dump_exclude(0);
    }
    g_stage = IDLE;
    g_child = g_queue = NULL;
    note_busy(cg_mono_ns());
    for (int i = 0; i < 2; i++)
        if (g_req[i] >= 0)
            close(g_req[i]), g_req[i] = -1;
    if (g_log >= 0)
        close(g_log), g_log = -1;
    if (g_ready) {
        posix_spawn_file_actions_destroy(&g_actions);
        posix_spawnattr_destroy(&g_attr);
        g_ready = false;
    }
}
