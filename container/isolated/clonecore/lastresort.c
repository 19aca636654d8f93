/*
 * lastresort.c - the container watchdog's last resort in isolated mode
 * (container/watchdog.py): a thread that never takes the GIL and, if the
 * watchdog is not re-armed in time, prints every thread's Python stack and
 * ends the container with status 1.
 *
 * Thread mode uses faulthandler.dump_traceback_later for this.  Isolated
 * mode cannot: that timer runs on CLOCK_MONOTONIC, and with --core-dumps a
 * node that crashed holding the GIL keeps it until gdb has written its dump
 * (dumps.c: seconds, 12 s seen on this project's machine, up to gdb's
 * bound), a wait in which no Python runs and which is no hang.  This one
 * runs on the watch clock (cg_watch_clock_ns), which stands still while a
 * dump is asked for or under way.
 *
 * Like faulthandler's, the dump reads the frames of threads that may be
 * running; it is only for when the watchdog's own Python thread could not
 * run.  One at a time: the watchdog's, then the shutdown bound's.
 */
#define Py_BUILD_CORE 1
#include <Python.h>
#include "internal/pycore_traceback.h" /* _Py_DumpTracebackThreads */

#include <errno.h>
#include <linux/futex.h>
#include <pthread.h>
#include <signal.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include "core.h"
#include "lastresort.h"
#include "dumps.h"
#include "sigsafe.h"

/* How long to wait before looking again when not armed (the first arm
   comes right after the start). */
#define UNARMED_NS 100000000

static pthread_t g_thread;
static bool g_running;
static int g_fd;
static char g_banner[512];
static PyInterpreterState *g_interp;
static int64_t g_due; /* on the watch clock; 0: not armed */
static int g_stop;    /* futex word: 1 ends the thread */

static void *watch(void *arg)
{
    (void)arg;
    /* Sleeping `left` on CLOCK_MONOTONIC is never too long: the watch
       clock goes no faster (it stands still during dumps), so on waking it
       has gone at most that far, and the thread looks again. */
    while (!__atomic_load_n(&g_stop, __ATOMIC_ACQUIRE)) {
        int64_t due = __atomic_load_n(&g_due, __ATOMIC_ACQUIRE);
        int64_t left = due ? due - cg_watch_clock_ns() : UNARMED_NS;
        if (left <= 0) {
            ss_write_all(g_fd, g_banner, strlen(g_banner));
            const char *err = _Py_DumpTracebackThreads(g_fd, g_interp, NULL);
            if (err) {
                ss_write_all(g_fd, err, strlen(err));
                ss_write_all(g_fd, "\n", 1);
            }
            _exit(1);
        }
        struct timespec ts = {left / 1000000000, left % 1000000000};
        syscall(SYS_futex, &g_stop, FUTEX_WAIT_PRIVATE, 0, &ts, NULL, 0);
    }
    return NULL;
}

/* Start the thread, not armed; it writes to fd, `banner` first. */
int cg_lastresort_start(int fd, const char *banner)
{
    if (g_running)
        return -EALREADY;
    size_t n = strlen(banner);
    if (n >= sizeof g_banner)
        return -ENAMETOOLONG;
    memcpy(g_banner, banner, n + 1);
    g_fd = fd;
    g_interp = PyInterpreterState_Main();
    g_due = 0;
    g_stop = 0;
    /* Every signal goes to the container's other threads. */
    sigset_t all, old;
    sigfillset(&all);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    int r = pthread_create(&g_thread, NULL, watch, NULL);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (r)
        return -r;
    pthread_setname_np(g_thread, "cg-lastresort");
    g_running = true;
    return 0;
}

/* Dump and exit once the watch clock has gone on `after_ns` from now,
   unless armed again or stopped first. */
void cg_lastresort_arm(int64_t after_ns)
{
    __atomic_store_n(&g_due, cg_watch_clock_ns() + after_ns, __ATOMIC_RELEASE);
}

void cg_lastresort_stop(void)
{
    if (!g_running)
        return;
    __atomic_store_n(&g_stop, 1, __ATOMIC_RELEASE);
    syscall(SYS_futex, &g_stop, FUTEX_WAKE_PRIVATE, 1, NULL, NULL, 0);
    pthread_join(g_thread, NULL);
    g_running = false;
}
