/*
 * herald.c - a node's CRASHED event, published by the core itself (the
 * words that describe the death: deathtext.c).
 *
 * Through Python, a death reached its CRASHED publish 0.3-0.4 ms after the
 * monitor's record (bench/README.md, "step by step"): the listener thread,
 * woken cold, decodes the record, takes the GIL and walks the host's and
 * the manager's bookkeeping before the publish.  Here the monitor claims
 * the event as it writes the record and hands it to the herald thread,
 * which publishes it through rcl (rclglue's cgr_event_publish): no Python and
 * no GIL on the way, so the event also goes out when a dead node left the
 * GIL unusable.  Python still does the rest (log, bookkeeping), and does
 * not publish what the record says was announced (CG_EVF_CLAIMED).
 *
 * Who owns an armed node's event, one word (cg_child.herald_state):
 *   OFF -> ARMED        cg_herald_arm (Python), once the node's LOADED is out
 *   ARMED -> CLAIMED    the monitor, at the node's death (herald_claim)
 *   ARMED -> OFF        cg_herald_disarm (Python: unload, abort, shutdown)
 * Whoever moves it from ARMED owns the event made at arming.  A CLAIMED
 * node is dead and its CRASHED out (or on its way): Python neither lists
 * it nor unloads it any more.
 *
 * The monitor claims only a death whose event says nothing Python alone
 * knows: not with a protection-key fault (the victim's name), the frame it
 * held the GIL in, or a core dump asked for.  Python does not arm with a
 * restart policy (the event says what it decided) and disarms before it
 * aborts a node (the event says why).
 *
 * The monitor never publishes itself: a dead node may hold a lock of Fast
 * DDS's, and the monitor must go on reaping whatever happens.  Nor does it
 * allocate (a dead node may hold an allocator lock): it serializes into the
 * buffer made at arming and passes its pointer down a non-blocking pipe.
 * The lock it takes for that (g_lock) is held by others only to flip the
 * herald on and off, around nothing that can block.  With MAX_IN_FLIGHT
 * events handed over and not yet published (a herald stuck in Fast DDS, on
 * a lock a dead node held), the monitor claims no more and Python publishes,
 * as without the herald; the ones already handed over wait with the herald.
 *
 * The event is rosidl's C message for cloneguard_interfaces/msg/ComponentEvent,
 * which Python makes at arming from the CRASHED event it would publish
 * itself (container/events.py), so that every field known at load is
 * Python's, defined by the .msg alone.  What only the death tells (exit
 * signal or code, allocator_quarantined, error_message) the monitor writes
 * into it through rclglue's cgr_event_write_death, which knows the
 * generated layout and allocates nothing (error_message's buffer was made
 * CG_DEATH_TEXT long).  This file never sees the layout: the message is a
 * void * with rclglue's functions and rosidl's destroy.
 */
#include "core.h"
#include "herald.h"

#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

enum { OFF = 0, ARMED = 1, CLAIMED = 2 };

typedef int (*publish_fn)(const void *publisher, void *msg, char *err, size_t err_size);
typedef void (*write_death_fn)(void *msg, int32_t exit_signal, int32_t exit_code, int quarantined,
                               const char *text);
typedef void (*destroy_fn)(void *msg);

struct cg_herald {      /* one armed node's event, one allocation */
    void *msg;          /* its ComponentEvent (rosidl's C message) */
    destroy_fn destroy; /* rosidl's: finalizes and frees msg */
    int32_t pid;
    char full_node_name[]; /* for a failure's words */
};

struct herald_thread { /* what one herald thread works with: its own,
                          so that a stuck one (cg_herald_stop) never
                          touches what a later one uses */
    int fd;            /* the pipe's read end */
    publish_fn publish;
    write_death_fn write_death;
    const void *publisher;
    long in_flight; /* handed to it, not yet published (atomic) */
};

#define MAX_IN_FLIGHT 32 /* events handed to the herald, not yet published */

static pthread_mutex_t g_lock = PTHREAD_MUTEX_INITIALIZER; /* the four below */
static int g_on;          /* the herald runs: the monitor may claim */
static int g_pipe_w = -1; /* the pipe's write end */
static pthread_t g_thread;
static struct herald_thread *g_self; /* the running herald's */
static long g_failed;                /* publishes that failed, ever (atomic) */

static void herald_free(struct cg_herald *h)
{
    h->destroy(h->msg);
    free(h);
}

/* ---- the herald thread ----------------------------------------------------- */

static void say(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static void say(const char *fmt, ...)
{
    /* write(2), not stdio: a dead node may hold stderr's FILE lock. */
    char line[512];
    va_list ap;
    va_start(ap, fmt);
    int k = vsnprintf(line, sizeof line, fmt, ap);
    va_end(ap);
    if (k > 0 && write(2, line, (size_t)k < sizeof line ? (size_t)k : sizeof line - 1) < 0) {
        /* nowhere else to say it */
    }
}

static void *herald_main(void *arg)
{
    struct herald_thread *self = arg;
    for (;;) {
        struct cg_herald *h;
        ssize_t n = read(self->fd, &h, sizeof h);
        if (n < 0 && errno == EINTR)
            continue;
        if (n != (ssize_t)sizeof h) { /* closed: cg_herald_stop */
            close(self->fd);
            free(self);
            return NULL;
        }
        char err[256] = "";
        if (self->publish(self->publisher, h->msg, err, sizeof err) != 0) { /* stamps it */
            __atomic_add_fetch(&g_failed, 1, __ATOMIC_RELAXED);
            say("cloneguard: the CRASHED event of %s (pid %d) was not published: %s\n",
                h->full_node_name, h->pid, err);
        }
        herald_free(h);
        __atomic_sub_fetch(&self->in_flight, 1, __ATOMIC_RELEASE);
    }
}

/* Start publishing armed nodes' CRASHED events with publish(publisher, ...),
   the death written into each with write_death (rclglue's cgr_event_publish
   and cgr_event_write_death, on the container's event publisher).  The
   publisher must outlive cg_herald_stop. */
int cg_herald_start(void *publish, void *write_death, const void *publisher)
{
    if (__atomic_load_n(&g_on, __ATOMIC_ACQUIRE))
        return -EALREADY;
    /* Everything made before g_lock is taken: the monitor may be waiting
       for it, and malloc may wait for an arena lock. */
    struct herald_thread *self = malloc(sizeof *self);
    if (!self)
        return -ENOMEM;
    int fds[2];
    if (pipe2(fds, O_CLOEXEC) < 0) {
        int err = errno;
        free(self);
        return -err;
    }
    fcntl(fds[1], F_SETFL, O_NONBLOCK); /* the monitor never waits */
    *self = (struct herald_thread){fds[0], (publish_fn)publish, (write_death_fn)write_death,
                                   publisher, 0};
    /* Signals go to the container's other threads (as for the monitor),
       but the ones a fault raises: the container's crash report names it. */
    sigset_t all, old;
    sigfillset(&all);
    sigdelset(&all, SIGSEGV), sigdelset(&all, SIGBUS), sigdelset(&all, SIGILL);
    sigdelset(&all, SIGFPE), sigdelset(&all, SIGABRT);
    pthread_sigmask(SIG_SETMASK, &all, &old);
    pthread_t thread;
    int r = -pthread_create(&thread, NULL, herald_main, self);
    pthread_sigmask(SIG_SETMASK, &old, NULL);
    if (r < 0) {
        close(fds[0]), close(fds[1]);
        free(self);
        return r;
    }
    pthread_setname_np(thread, "cg-herald");
    pthread_mutex_lock(&g_lock);
    bool running = g_on;
    if (!running) {
        g_pipe_w = fds[1];
        g_thread = thread;
        g_self = self;
        __atomic_store_n(&g_on, 1, __ATOMIC_RELEASE);
    }
    pthread_mutex_unlock(&g_lock);
    if (running) { /* another start came first: this one ends */
        close(fds[1]);
        pthread_join(thread, NULL);
        return -EALREADY;
    }
    return 0;
}

/* Claim no more deaths, publish the ones claimed, end the thread: 0, or
   -ETIMEDOUT if it is still inside a publish after timeout_ms (stuck on a
   lock of Fast DDS's a dead node held, say: it is left as it is, and its
   publisher must never be destroyed).  After it, every death is Python's
   to report. */
int cg_herald_stop(int timeout_ms)
{
    pthread_mutex_lock(&g_lock);
    int was = g_on;
    pthread_t thread = g_thread;
    if (was) {
        __atomic_store_n(&g_on, 0, __ATOMIC_RELEASE);
        close(g_pipe_w); /* the thread drains the pipe, reads EOF, ends
                            (and frees g_self: not touched after this) */
        g_pipe_w = -1;
        g_self = NULL;
    }
    pthread_mutex_unlock(&g_lock);
    if (!was)
        return -EALREADY;
    struct timespec until;
    clock_gettime(CLOCK_REALTIME, &until);
    until.tv_sec += timeout_ms / 1000;
    until.tv_nsec += (long)(timeout_ms % 1000) * 1000000;
    if (until.tv_nsec >= 1000000000)
        until.tv_sec++, until.tv_nsec -= 1000000000;
    if (pthread_timedjoin_np(thread, NULL, &until) != 0) {
        pthread_detach(thread);
        return -ETIMEDOUT;
    }
    return 0;
}

/* Events the herald failed to publish since the core was loaded. */
long cg_herald_failures(void)
{
    return __atomic_load_n(&g_failed, __ATOMIC_RELAXED);
}

/* ---- arming and claiming ---------------------------------------------- */

/* Arm c's CRASHED event (Python, once the node's LOADED is out): msg, its
   ComponentEvent with every field known at load, is the core's from now on
   (destroy finalizes and frees it); full_node_name and pid are for the
   words of a failed publish.  0; -EALREADY if armed or claimed (msg stays
   the caller's); -ENOMEM. */
int cg_herald_arm(struct cg_child *c, void *msg, void *destroy, const char *full_node_name, int pid)
{
    if (__atomic_load_n(&c->herald_state, __ATOMIC_ACQUIRE) != OFF)
        return -EALREADY;
    size_t len = strlen(full_node_name) + 1;
    struct cg_herald *h = malloc(sizeof *h + len);
    if (!h)
        return -ENOMEM;
    h->msg = msg;
    h->destroy = (destroy_fn)destroy;
    h->pid = pid;
    memcpy(h->full_node_name, full_node_name, len);
    c->herald = h;
    __atomic_store_n(&c->herald_state, ARMED, __ATOMIC_RELEASE);
    return 0;
}

/* Take c's event back (Python): 1 if its death, if any, is Python's to
   report now; 0 if the monitor claimed it (c is dead, its CRASHED out). */
int cg_herald_disarm(struct cg_child *c)
{
    int armed = ARMED;
    if (__atomic_compare_exchange_n(&c->herald_state, &armed, OFF, false, __ATOMIC_ACQ_REL,
                                    __ATOMIC_ACQUIRE)) {
        herald_free(c->herald);
        c->herald = NULL;
        return 1;
    }
    return armed != CLAIMED;
}

/* Was c's death announced by the herald? */
int cg_herald_claimed(const struct cg_child *c)
{
    return __atomic_load_n(&c->herald_state, __ATOMIC_ACQUIRE) == CLAIMED;
}

/* A block going away (cg_release, cg_abandon: c is reaped, so the monitor
   is done with it): free an event nobody claimed. */
void herald_forget(struct cg_child *c)
{
    if (__atomic_load_n(&c->herald_state, __ATOMIC_ACQUIRE) == ARMED) {
        herald_free(c->herald);
        c->herald = NULL;
        __atomic_store_n(&c->herald_state, OFF, __ATOMIC_RELEASE);
    }
}

/* On the monitor thread, at c's death (status, code as in its record),
   c->death_text written: announce it if armed and nothing in its event is
   Python's alone to say.  True if the herald has it. */
bool herald_claim(struct cg_child *c, int status, int code, bool quarantined)
{
    if (c->gil_code != NULL || c->core_dump != CG_CORE_NONE ||
        (c->crash_si_code == SEGV_PKUERR && c->crash_pkey) ||
        __atomic_load_n(&c->stop_requested, __ATOMIC_ACQUIRE) == CG_STOP_PARENT)
        return false;
    /* Under g_lock: once cg_herald_stop has run, nothing more goes down
       the pipe, and nothing is claimed that cannot go (a claim undone
       after a failed write would have looked announced meanwhile). */
    pthread_mutex_lock(&g_lock);
    bool sent = false;
    int armed = ARMED;
    if (g_on && __atomic_load_n(&g_self->in_flight, __ATOMIC_ACQUIRE) < MAX_IN_FLIGHT &&
        __atomic_compare_exchange_n(&c->herald_state, &armed, CLAIMED, false, __ATOMIC_ACQ_REL,
                                    __ATOMIC_ACQUIRE)) {
        struct cg_herald *h = c->herald;
        bool killed = code == CLD_KILLED || code == CLD_DUMPED;
        g_self->write_death(h->msg, killed ? status : 0, code == CLD_EXITED ? status : 0,
                            quarantined, c->death_text);
        __atomic_add_fetch(&g_self->in_flight, 1, __ATOMIC_ACQ_REL);
        sent = write(g_pipe_w, &h, sizeof h) == (ssize_t)sizeof h;
        if (sent) {
            c->herald = NULL; /* the herald frees it */
        } else {              /* cannot fail with room for MAX_IN_FLIGHT */
            __atomic_sub_fetch(&g_self->in_flight, 1, __ATOMIC_RELEASE);
            __atomic_store_n(&c->herald_state, ARMED, __ATOMIC_RELEASE); /* Python's */
        }
    }
    pthread_mutex_unlock(&g_lock);
    return sent;
}
