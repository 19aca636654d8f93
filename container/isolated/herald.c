/*
 * herald.c - a node's CRASHED event, published by the core itself (the
 * words that describe the death: deathtext.c).
 *
 * Through Python, a death reached its CRASHED publish 0.3-0.4 ms after the
 * monitor's record (bench/README.md, "step by step"): the listener thread,
 * woken cold, decodes the record, takes the GIL and walks the host's and
 * the manager's bookkeeping before the publish.  Here the monitor claims
 * the event as it writes the record and hands it to the herald thread,
 * which publishes it through rcl (rclglue's cgr_publish_cdr): no Python and
 * no GIL on the way, so the event also goes out when a dead node left the
 * GIL unusable.  Python still does the rest (log, bookkeeping), and does
 * not publish what the record says was announced (CG_EVF_CLAIMED).
 *
 * Who owns an armed node's event, one word (cg_child.herald_state):
 *   OFF -> ARMED        cg_herald_arm (Python), once the node's LOADED is out
 *   ARMED -> CLAIMED    the monitor, at the node's death (herald_claim)
 *   ARMED -> OFF        cg_herald_disarm (Python: unload, abort, shutdown)
 * Whoever moves it from ARMED owns the buffer made at arming.  A CLAIMED
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
 * The wire format (what rmw_fastrtps takes as a serialized message): CDR,
 * little-endian, encapsulation CDR_LE (00 01 00 00), then the fields of
 * cloneguard_interfaces/msg/ComponentEvent.msg in its order, each aligned
 * to its own size counted from the end of the 4-byte header; a string is a
 * uint32 length counting its NUL, its bytes, the NUL.  tests/test_herald.py
 * has rclpy deserialize what this writes.
 */
#include "core.h"

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
#define CDR_HEADER 4
#define EVENT_CRASHED 3     /* ComponentEvent.CRASHED */
#define STAMP_AT CDR_HEADER /* the stamp (sec, nanosec) is the first field */

struct cg_herald { /* one armed node's event, one allocation */
    uint64_t unique_id, start_time_ns;
    int32_t pid;
    const char *full_node_name, *package_name, *plugin_name; /* in text[] */
    size_t len;                                              /* of cdr[] in use */
    uint8_t *cdr;                                            /* after text[] */
    char text[];
};

typedef int (*publish_fn)(const void *publisher, uint8_t *cdr, size_t len, char *err,
                          size_t err_size);

struct herald_thread { /* what one herald thread works with: its own,
                          so that a stuck one (cg_herald_stop) never
                          touches what a later one uses */
    int fd;            /* the pipe's read end */
    publish_fn publish;
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

/* ---- CDR ----------------------------------------------------------------- */

struct cdr {
    uint8_t *p;
    size_t n;
};

static void put(struct cdr *w, const void *v, size_t size)
{
    while ((w->n - CDR_HEADER) % size)
        w->p[w->n++] = 0;
    memcpy(w->p + w->n, v, size);
    w->n += size;
}

static void put_string(struct cdr *w, const char *s)
{
    uint32_t len = (uint32_t)strlen(s) + 1;
    put(w, &len, sizeof len);
    memcpy(w->p + w->n, s, len);
    w->n += len;
}

/* Room a CRASHED event needs beyond its strings' bytes: header, fixed-size
   fields, lengths, NULs and alignment (less than 96). */
#define CDR_ROOM 128

/* Serialize h's event, dead of (status, code), with error_message text. */
static void serialize(struct cg_herald *h, int status, int code, bool quarantined, const char *text)
{
    struct cdr w = {h->cdr, 0};
    static const uint8_t CDR_LE[CDR_HEADER] = {0x00, 0x01, 0x00, 0x00};
    memcpy(w.p, CDR_LE, CDR_HEADER);
    w.n = CDR_HEADER;
    int32_t sec = 0;
    uint32_t nanosec = 0; /* stamped by the herald, just before the publish */
    uint8_t type = EVENT_CRASHED, q = quarantined;
    bool killed = code == CLD_KILLED || code == CLD_DUMPED;
    int32_t exit_signal = killed ? status : 0, exit_code = code == CLD_EXITED ? status : 0;
    put(&w, &sec, 4);
    put(&w, &nanosec, 4);
    put(&w, &type, 1);
    put(&w, &h->unique_id, 8);
    put_string(&w, h->full_node_name);
    put_string(&w, h->package_name);
    put_string(&w, h->plugin_name);
    put_string(&w, text);
    put(&w, &h->pid, 4);
    put(&w, &exit_signal, 4);
    put(&w, &exit_code, 4);
    put(&w, &h->start_time_ns, 8);
    put(&w, &q, 1);
    put_string(&w, ""); /* repaired_state */
    h->len = w.n;
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
        struct timespec now;
        clock_gettime(CLOCK_REALTIME, &now);
        int32_t sec = (int32_t)now.tv_sec;
        uint32_t nanosec = (uint32_t)now.tv_nsec;
        memcpy(h->cdr + STAMP_AT, &sec, 4);
        memcpy(h->cdr + STAMP_AT + 4, &nanosec, 4);
        char err[256] = "";
        if (self->publish(self->publisher, h->cdr, h->len, err, sizeof err) != 0) {
            __atomic_add_fetch(&g_failed, 1, __ATOMIC_RELAXED);
            say("cloneguard: the CRASHED event of %s (pid %d) was not published: %s\n",
                h->full_node_name, h->pid, err);
        }
        free(h);
        __atomic_sub_fetch(&self->in_flight, 1, __ATOMIC_RELEASE);
    }
}

/* Start publishing armed nodes' CRASHED events with publish(publisher, ...)
   (rclglue's cgr_publish_cdr, on the container's event publisher).  The
   publisher must outlive cg_herald_stop. */
int cg_herald_start(void *publish, const void *publisher)
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
    *self = (struct herald_thread){fds[0], (publish_fn)publish, publisher, 0};
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

/* Arm c's CRASHED event with its fixed fields (Python, once its LOADED is
   out).  0; -EALREADY if armed or claimed; -ENOMEM. */
int cg_herald_arm(struct cg_child *c, uint64_t unique_id, const char *full_node_name,
                  const char *package_name, const char *plugin_name, int pid,
                  uint64_t start_time_ns)
{
    if (__atomic_load_n(&c->herald_state, __ATOMIC_ACQUIRE) != OFF)
        return -EALREADY;
    size_t l1 = strlen(full_node_name) + 1, l2 = strlen(package_name) + 1;
    size_t l3 = strlen(plugin_name) + 1;
    size_t cap = CDR_ROOM + l1 + l2 + l3 + CG_DEATH_TEXT;
    struct cg_herald *h = malloc(sizeof *h + l1 + l2 + l3 + cap);
    if (!h)
        return -ENOMEM;
    h->unique_id = unique_id;
    h->start_time_ns = start_time_ns;
    h->pid = pid;
    char *t = h->text;
    h->full_node_name = memcpy(t, full_node_name, l1);
    h->package_name = memcpy(t + l1, package_name, l2);
    h->plugin_name = memcpy(t + l1 + l2, plugin_name, l3);
    h->cdr = (uint8_t *)(t + l1 + l2 + l3);
    h->len = 0;
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
        free(c->herald);
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
        free(c->herald);
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
        serialize(h, status, code, quarantined, c->death_text);
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
