/*
 * gilrepair.c - put CPython's GIL back in order after a child died in it.
 *
 * Built with Py_BUILD_CORE against the internal headers of the interpreter
 * the extension is compiled for (3.11.7 here): _PyRuntime.ceval.gil and
 * _PyRuntime.gilstate are read and written by name.  assumptions.py checks
 * at start-up that the running interpreter is that one (cg_gil_probe).
 *
 * CPython 3.11's GIL (Python/ceval_gil.h) is `locked` + `last_holder`
 * guarded by `mutex`, waiters on `cond` (timed waits, 5 ms), and a hand-over
 * pair `switch_mutex`/`switch_cond` (the dropping thread waits until someone
 * else took it; an untimed wait).  take_gil: lock mutex; while locked: timed
 * wait on cond; then lock switch_mutex, locked = 1, last_holder = me,
 * signal switch_cond, unlock switch_mutex; unlock mutex.  drop_gil:
 * last_holder = me; lock mutex, locked = 0, signal cond, unlock mutex; then
 * maybe lock switch_mutex and wait on switch_cond.  Both mutexes are
 * default-kind (non-robust) glibc mutexes; both condvars are glibc 2.36
 * condvars.
 *
 * A child killed anywhere in there leaves one of:
 *   1. the GIL locked with last_holder = its thread state   -> release it
 *   2. mutex or switch_mutex owned by its tid               -> take over,
 *      decide the GIL state under it, unlock
 *   3. a waiter registration in cond or switch_cond holding a reference on
 *      its condvar group: the next signaller that has to close that group
 *      waits for the reference to go, forever (glibc 2.36's group switch)
 *                                                           -> cancel it
 *      the way pthread_cancel would: glibc's own cleanup routine, which the
 *      waiter registered in its struct pthread (.cleanup) before blocking;
 *      a waiter that crashed and waits in its handler for its core dump
 *      (dumps.c) will never return to its wait either: its reference is
 *      dropped as soon as it asks (cg_gil_step_aside), the rest at death
 *   4. a condvar's internal lock taken (it died signalling)  -> clear it,
 *      holding the condvar's mutex, once every live task that could hold
 *      it is seen blocked elsewhere (unstick_cond_lock: no owner is
 *      recorded, so its holder is proven dead by accounting, never by time)
 * This file is called by the monitor after a death, before the child is
 * reaped (so its tid cannot be reused meanwhile).  It never takes the GIL.
 */
#define Py_BUILD_CORE 1
#include <Python.h>
#include "internal/pycore_runtime.h"   /* _PyRuntime, _gil_runtime_state */
#include "internal/pycore_pystate.h"   /* _PyThreadState_SetCurrent */
#include "internal/pycore_traceback.h" /* _Py_DumpTraceback */
#include "internal/pycore_frame.h"     /* _PyInterpreterFrame (cg_record_py_stack) */

#ifndef _GNU_SOURCE
#define _GNU_SOURCE
#endif
#include <dlfcn.h>
#include <errno.h>
#include <limits.h>
#include <link.h>
#include <linux/futex.h>
#include <pthread.h>
#include <signal.h>
#include <stdbool.h>
#include <string.h>
#include <sys/syscall.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "repair.h"
#include "sigsafe.h"

#define GIL (&_PyRuntime.ceval.gil)
#define ANON ((struct cg_dead *)-1) /* a dead owner we cannot name */

static void sleep_us(long us)
{
    struct timespec ts = {us / 1000000, (us % 1000000) * 1000};
    while (nanosleep(&ts, &ts) < 0 && errno == EINTR) {
    }
}

static void futex_wake(void *addr, int n, int private_)
{
    syscall(SYS_futex, addr, FUTEX_WAKE | (private_ ? FUTEX_PRIVATE_FLAG : 0), n, NULL, NULL, 0);
}

/* Is task `tid` dead?  One of the dead we were given, gone altogether, or
   a zombie child of ours (a death the monitor has not handled yet).  A
   zombie still answers kill(pid, 0); a dead non-leader thread does not. */
static bool is_dead(pid_t tid, struct cg_dead *d, int n, struct cg_dead **who)
{
    *who = NULL;
    if (tid <= 0)
        return false;
    for (int i = 0; i < n; i++)
        if (d[i].pid == tid) {
            *who = &d[i];
            return true;
        }
    if (kill(tid, 0) < 0 && errno == ESRCH)
        return true;
    siginfo_t si;
    memset(&si, 0, sizeof si);
    return waitid(P_PID, (id_t)tid, &si, WEXITED | WNOHANG | WNOWAIT | __WALL) == 0 &&
           si.si_pid == tid;
}

static void credit(struct cg_dead *who, uint32_t bit, uint32_t *misc)
{
    if (who && who != ANON)
        who->repairs |= bit;
    else
        *misc |= bit;
}

/* If m is locked by a dead task, make the calling thread its owner (the
   dead cannot unlock it and nobody else can lock it, so nothing races with
   this) and return the dead task (ANON if unnamed); else NULL.
   glibc (default kind) writes __owner right after taking the lock word and
   clears it right before releasing it: a lock word with owner 0 is a thread
   inside that window, which a live thread leaves within microseconds. */
static struct cg_dead *take_over(pthread_mutex_t *m, struct cg_dead *d, int n)
{
    for (int waited_ms = 0;; waited_ms++) {
        int lock = __atomic_load_n(&m->__data.__lock, __ATOMIC_ACQUIRE);
        pid_t owner = __atomic_load_n(&m->__data.__owner, __ATOMIC_ACQUIRE);
        if (lock == 0)
            return NULL;
        struct cg_dead *who = NULL;
        if (owner != 0) {
            if (!is_dead(owner, d, n, &who))
                return NULL;
            if (!who)
                who = ANON;
        } else if (waited_ms < 200) {
            sleep_us(1000);
            continue;
        } else {
            who = ANON; /* died between lock word and owner store */
        }
        __atomic_store_n(&m->__data.__owner, (int)syscall(SYS_gettid), __ATOMIC_RELEASE);
        return who;
    }
}

/* Lock m for the repair, taking it over if a dead task turns out to own it
   (a death after step 1 looked).  false after ~2 s of a live holder. */
static bool lock_for_repair(pthread_mutex_t *m, uint32_t bit, struct cg_dead *d, int n,
                            uint32_t *misc)
{
    for (int i = 0; i < 40; i++) {
        struct timespec ts;
        clock_gettime(CLOCK_MONOTONIC, &ts);
        ts.tv_nsec += 50 * 1000000;
        if (ts.tv_nsec >= 1000000000)
            ts.tv_sec++, ts.tv_nsec -= 1000000000;
        if (pthread_mutex_clocklock(m, CLOCK_MONOTONIC, &ts) == 0)
            return true;
        struct cg_dead *who = take_over(m, d, n);
        if (who) {
            credit(who, bit, misc);
            return true;
        }
    }
    return false;
}

/* Lock gil->mutex, taking it over if a dead task turns out to hold it.
   false after ~2 s of a live holder (then the GIL is not checked). */
static bool lock_gil_mutex(struct cg_dead *d, int n, uint32_t *misc)
{
    if (lock_for_repair(&GIL->mutex, CG_REPAIR_GIL_MUTEX, d, n, misc))
        return true;
    *misc |= CG_REPAIR_GIL_TIMEOUT;
    return false;
}

/* With gil->mutex held: nobody is inside take_gil's hand-over, so if the
   GIL is locked, last_holder is the live thread state of its holder.  If
   that holder's thread is dead, release the GIL in its name. */
static void release_if_held_by_dead(struct cg_dead *d, int n, int interp, uint32_t *misc)
{
    struct _gil_runtime_state *gil = GIL;
    if (!_Py_atomic_load_relaxed(&gil->locked))
        return;
    PyThreadState *h = (PyThreadState *)_Py_atomic_load_relaxed(&gil->last_holder);
    struct cg_dead *who;
    if (!h || !is_dead((pid_t)h->native_thread_id, d, n, &who))
        return;
    /* While the GIL is still the dead task's, nobody runs Python: what it
       may have left half-done in the interpreter first (interp.c). */
    /* Where it was: its innermost frame (the frames stay, with the dead
       thread state, until the child is released). */
    _PyCFrame *cframe;
    _PyInterpreterFrame *frame, top;
    PyTypeObject *code_type;
    if (who && PEEK(&h->cframe, cframe) && cframe && PEEK(&cframe->current_frame, frame) && frame &&
        PEEK(frame, top) && top.f_code && PEEK(&top.f_code->ob_base.ob_base.ob_type, code_type) &&
        code_type == &PyCode_Type) { /* a frame being pushed or popped can be torn */
        who->gil_code = top.f_code;
        who->gil_lasti = _PyInterpreterFrame_LASTI(&top);
    }
    uint32_t mended = interp ? cg_interp_after_gil_death(who ? who->slot : 0, h) : 0;
    for (uint32_t bit = 1; mended; bit <<= 1)
        if (mended & bit) {
            credit(who, bit, misc);
            mended &= ~bit;
        }
    /* It may have swapped itself out already (drop_gil's first step). */
    uintptr_t expected = (uintptr_t)h;
    __atomic_compare_exchange_n(&_PyRuntime.gilstate.tstate_current._value, &expected, 0, false,
                                __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST);
    _Py_atomic_store(&gil->locked, 0);
    credit(who, CG_REPAIR_GIL_RELEASED, misc);
}

/* A condvar's internal lock (low 2 bits of __g1_orig_size, glibc 2.36
   nptl/pthread_cond_common.c: 0 free, 1 taken, 2 taken with futex waiters)
   records no owner, so it may be cleared only when its holder is proven
   dead.  Who can hold it (glibc 2.36):
     - a signaller, inside pthread_cond_signal/broadcast.  CPython signals
       gil->cond only in drop_gil holding gil->mutex, and switch_cond only
       in take_gil holding switch_mutex; the repair's own calls run here;
     - a waiter that stopped waiting without a signal (a timeout, or
       cancellation): __condvar_cancel_waiting and the replacement signal it
       may send, without the mutex, but while it still counts in __wrefs >> 3
       (its wake-up is confirmed only afterwards).  It may block holding the
       lock, in a signal's group switch waiting for group references.
   The caller holds the condvar's mutex: then no live signaller exists and
   no waiter can register (that is done holding the mutex), so __wrefs >> 3
   only decreases, and a live holder is a registered waiter.
     - switch_cond (timed = false): its waits are untimed and never
       cancelled, so no waiter ever takes the lock: its holder is dead.
     - gil->cond (timed): a registered waiter blocked in FUTEX_WAIT on the
       lock word is not its holder.  FUTEX_WAKE returns how many were
       (woken, they re-check and block again: acquire_lock loops).  Proof:
       the lock is taken, then __wrefs >> 3 (read next) <= blocked +
       `dead_registered` (dead waiters known to be registered, being
       cancelled).  A live holder -- or a live waiter that a release just
       woke -- is registered and not blocked there, so the count falls
       short; so does a dead registered waiter we do not know of.  Waiters
       blocked on __g_signals are not counted (woken, they could time out
       and take the lock before we clear it): they time out within 5 ms and
       then either leave (confirmed, and they cannot register again while
       we hold the mutex) or block on the lock word, so this tries for up to
       ~2 s.
   true: free, or cleared (the dead cannot release it and nobody alive can
   take it before we clear it).  false: still taken by a holder not proven
   dead, left as it is (a hang at worst, never a broken lock); anything
   that takes it now may wait forever. */
static bool unstick_cond_lock(pthread_cond_t *c, bool timed, unsigned dead_registered,
                              uint32_t *misc)
{
    unsigned *w = &c->__data.__g1_orig_size;
    int private_ = (c->__data.__wrefs & 1) == 0; /* bit 0: process-shared */
    /* Each count wakes the waiters it counts; they must run to block again
       before the next one.  On a loaded machine that took more than the
       1 ms this once slept (deep run under -n 2: 3 hangs in 600 payload
       trials, a live drop_gil left waiting for the lock), so the pause
       doubles up to 32 ms, for ~2 s in all. */
    long pause_us = 1000;
    for (int i = 0; i < 70; i++) {
        if ((__atomic_load_n(w, __ATOMIC_ACQUIRE) & 3) == 0)
            return true;
        bool dead_holder = !timed;
        if (timed) {
            unsigned registered = __atomic_load_n(&c->__data.__wrefs, __ATOMIC_ACQUIRE) >> 3;
            long blocked = syscall(SYS_futex, w, FUTEX_WAKE | (private_ ? FUTEX_PRIVATE_FLAG : 0),
                                   INT_MAX, NULL, NULL, 0);
            dead_holder = blocked >= 0 && registered <= (unsigned long)blocked + dead_registered;
        }
        if (dead_holder) {
            unsigned old = __atomic_fetch_and(w, ~3u, __ATOMIC_RELEASE);
            if ((old & 3) == 2)
                futex_wake(w, 1, private_);
            *misc |= CG_REPAIR_COND_LOCK;
            return true;
        }
        sleep_us(pause_us);
        if (pause_us < 32000)
            pause_us *= 2;
    }
    return false;
}

/* A dead task blocked in pthread_cond_wait on one of the GIL's condvars. */
struct waiter {
    struct cg_dead *who;
    struct _pthread_cleanup_buffer *buf;
    struct cg_cond_cbuf *cb;
    pthread_cond_t *cond;
    pthread_mutex_t *mutex;
    uint32_t bit;
};

static bool inside(const void *p, size_t len, const struct cg_dead *d)
{
    return (const char *)p >= d->stack_lo && (const char *)p + len <= d->stack_hi;
}

static bool find_waiter(struct cg_dead *d, const struct cg_repair_cfg *cfg, struct waiter *w)
{
    struct _gil_runtime_state *gil = GIL;
    struct _pthread_cleanup_buffer *buf =
        *(struct _pthread_cleanup_buffer **)(d->tcb + cfg->cleanup_off);
    if (!buf || !inside(buf, sizeof *buf, d) || (uintptr_t)buf->__routine != cfg->cond_cleanup)
        return false;
    struct cg_cond_cbuf *cb = buf->__arg;
    if (!inside(cb, sizeof *cb, d))
        return false;
    if (cb->cond == &gil->cond && cb->mutex == &gil->mutex)
        w->bit = CG_REPAIR_COND_WAITER;
    else if (cb->cond == &gil->switch_cond && cb->mutex == &gil->switch_mutex)
        w->bit = CG_REPAIR_SWITCH_WAITER;
    else
        return false; /* some other condvar: not ours to touch */
    w->who = d, w->buf = buf, w->cb = cb;
    w->cond = cb->cond, w->mutex = cb->mutex;
    return true;
}

/* The group reference a blocked waiter holds (__g_refs[g] counts 2 per
   reference, bit 0 asks the last one out to wake the closing signaller). */
static void drop_group_ref(struct waiter *w)
{
    unsigned *r = &w->cond->__data.__g_refs[w->cb->wseq & 1];
    if (__atomic_fetch_sub(r, 2, __ATOMIC_RELEASE) == 3) {
        __atomic_fetch_and(r, ~1u, __ATOMIC_RELAXED);
        /* __wrefs bit 0: process-shared (the GIL's are private) */
        futex_wake(r, INT_MAX, (w->cond->__data.__wrefs & 1) == 0);
    }
}

static void take_group_ref(struct waiter *w)
{
    __atomic_fetch_add(&w->cond->__data.__g_refs[w->cb->wseq & 1], 2, __ATOMIC_ACQUIRE);
}

/* How many of w[from..nw) wait on c: dead, registered, not cancelled yet. */
static unsigned pending_on(const struct waiter *w, int nw, int from, const pthread_cond_t *c)
{
    unsigned k = 0;
    for (int i = from; i < nw; i++)
        k += w[i].cond == c;
    return k;
}

bool cg_gil_step_aside(struct cg_dead *d, const struct cg_repair_cfg *cfg)
{
    struct waiter w;
    if (!cfg->condvar || !cfg->cond_cleanup || !find_waiter(d, cfg, &w))
        return false;
    /* Its futex wait is interrupted by the crash handler, which ends in
       the task's death: the wait never resumes to drop the reference
       itself.  Its registration stays for the repair to cancel. */
    drop_group_ref(&w);
    return true;
}

uint32_t cg_gil_repair(struct cg_dead *d, int n, const struct cg_repair_cfg *cfg)
{
    struct _gil_runtime_state *gil = GIL;
    uint32_t misc = 0;
    bool checked = false, wake_switch = false;

    /* 0. Dead waiters of cond / switch_cond, and their group references
       dropped first: a signal closing their group (a live drop_gil, or a
       live waiter's replacement signal) waits for them holding the
       condvar's internal lock; with them gone it goes on and lets go.
       With several dead waiters one cleanup could wait for another's
       reference, so all go first and each is taken back just before its
       own cleanup drops it (step 2). */
    struct waiter w[16];
    int nw = 0;
    if (cfg->condvar && cfg->cond_cleanup) {
        for (int i = 0; i < n && nw < 16; i++)
            if (find_waiter(&d[i], cfg, &w[nw]))
                nw++;
        for (int i = 0; i < nw; i++)
            if (!w[i].who->ref_dropped) /* else cg_gil_step_aside did */
                drop_group_ref(&w[i]);
    }

    /* 1. Mutexes a dead task owns.  If it owned both, it was in take_gil's
       hand-over, entered only with the GIL free: whatever `locked` and
       `last_holder` say, nobody alive holds the GIL.  Each condvar is
       signalled only holding its mutex (gil->cond in drop_gil, switch_cond
       in take_gil's hand-over), so a dead owner may have died inside that
       signal holding the condvar's internal lock, which the next signal
       would wait for forever (seen: 1 in 300 deep payload trials, drop_gil).
       Holding the mutex we can tell whether its holder is dead. */
    if (cfg->gil) {
        struct cg_dead *wm = take_over(&gil->mutex, d, n);
        struct cg_dead *ws = take_over(&gil->switch_mutex, d, n);
        if (wm)
            credit(wm, CG_REPAIR_GIL_MUTEX, &misc);
        if (ws)
            credit(ws, CG_REPAIR_SWITCH_MUTEX, &misc), wake_switch = true;
        if (wm) {
            if (ws && (wm == ws || wm == ANON || ws == ANON)) {
                if (_Py_atomic_load_relaxed(&gil->locked)) {
                    _Py_atomic_store(&gil->locked, 0);
                    credit(wm, CG_REPAIR_GIL_RELEASED, &misc);
                }
            } else {
                release_if_held_by_dead(d, n, cfg->interp, &misc);
            }
            if (cfg->condvar)
                unstick_cond_lock(&gil->cond, true, pending_on(w, nw, 0, &gil->cond), &misc);
            checked = true;
            pthread_mutex_unlock(&gil->mutex);
        }
        if (ws) {
            if (cfg->condvar)
                unstick_cond_lock(&gil->switch_cond, false, 0, &misc);
            pthread_mutex_unlock(&gil->switch_mutex);
        }
    }

    /* 2. Cancel each dead waiter.  glibc's cleanup routine cancels a
       waiter exactly as pthread_cancel would: drops its group reference,
       takes it out of its group (sending a replacement signal if it had
       consumed one), and re-locks the mutex, which we unlock.  Taking it
       out needs the condvar's internal lock: first, under the mutex, make
       sure no dead task holds it (else the cleanup would wait forever; if
       that cannot be proven, the waiter is left as it is). */
    for (int i = 0; i < nw; i++) {
        uint32_t mbit = w[i].mutex == &gil->mutex ? CG_REPAIR_GIL_MUTEX : CG_REPAIR_SWITCH_MUTEX;
        if (!lock_for_repair(w[i].mutex, mbit, d, n, &misc))
            continue;
        bool free_ = unstick_cond_lock(w[i].cond, w[i].cond == &gil->cond,
                                       pending_on(w, nw, i, w[i].cond), &misc);
        pthread_mutex_unlock(w[i].mutex);
        if (!free_)
            continue;
        take_group_ref(&w[i]);
        w[i].buf->__routine(w[i].cb); /* returns holding mutex */
        *(void **)(w[i].who->tcb + cfg->cleanup_off) = w[i].buf->__prev;
        if (w[i].mutex == &gil->mutex && cfg->gil && !checked) {
            release_if_held_by_dead(d, n, cfg->interp, &misc);
            checked = true;
        }
        pthread_mutex_unlock(w[i].mutex);
        credit(w[i].who, w[i].bit, &misc);
        wake_switch = true;
    }

    /* 3. The GIL itself, if step 1 did not look at it. */
    if (cfg->gil && !checked && lock_gil_mutex(d, n, &misc)) {
        release_if_held_by_dead(d, n, cfg->interp, &misc);
        pthread_mutex_unlock(&gil->mutex);
    }

    /* 4. A thread that dropped the GIL for the dead one may be waiting
       (untimed) on switch_cond for a hand-over that will not come.  Waiters
       on cond need nothing: their waits time out every 5 ms.  The
       broadcast takes switch_cond's internal lock: not if a holder not
       proven dead keeps it (the monitor would wait forever). */
    bool released = misc & CG_REPAIR_GIL_RELEASED;
    for (int i = 0; i < n; i++)
        released |= (d[i].repairs & CG_REPAIR_GIL_RELEASED) != 0;
    if (cfg->gil && (wake_switch || released)) {
        bool free_ = true;
        if (cfg->condvar &&
            (__atomic_load_n(&gil->switch_cond.__data.__g1_orig_size, __ATOMIC_ACQUIRE) & 3) != 0) {
            free_ = lock_for_repair(&gil->switch_mutex, CG_REPAIR_SWITCH_MUTEX, d, n, &misc);
            if (free_) {
                free_ = unstick_cond_lock(&gil->switch_cond, false, 0, &misc);
                pthread_mutex_unlock(&gil->switch_mutex);
            }
        }
        if (free_)
            pthread_cond_broadcast(&gil->switch_cond);
    }
    return misc;
}

/* ---------------------------------------------------------------------- */
/* A child's thread state.  Creating and deleting one takes the runtime's
   HEAD_LOCK (a semaphore: no owner, so no repair if its holder dies), so the
   child does neither: the parent creates it before the clone, the child
   binds it to itself, and release() deletes it after the child is reaped. */

PyThreadState *cg_tstate_new(void) /* parent; any thread, no GIL */
{
    return _PyThreadState_Prealloc(PyInterpreterState_Main());
}

void cg_tstate_bind(PyThreadState *ts) /* child, before it runs Python */
{
    ts->thread_id = PyThread_get_thread_ident(); /* pthread_self() */
    ts->native_thread_id = (unsigned long)syscall(SYS_gettid);
    /* PyGILState's TSS slot lives in our TLS block, which an earlier child
       may have used (the allocator guard's contexts are reused), and
       CPython 3.11 binds a thread state only to an empty slot.  The earlier
       child's thread state is deleted from a container thread (release),
       whose own slot that clears, never this one; a crashed child's is
       never deleted.  So the slot may still name it: PyGILState_Ensure and
       the crash report (cg_record_py_stack) then used the dead child's
       thread state.  Empty it first. */
    PyThread_tss_set(&_PyRuntime.gilstate.autoTSSkey, NULL);
    _PyThreadState_SetCurrent(ts);
}

/* ---------------------------------------------------------------------- */

int cg_gil_probe(struct cg_gil_probe *out)
{
    struct _gil_runtime_state *gil = GIL;
    memset(out, 0, sizeof *out);
    out->compiled_hex = PY_VERSION_HEX;
    out->running_hex = Py_Version;
    out->runtime_size_compiled = (long)sizeof(_PyRuntimeState);
    Dl_info info;
    const ElfW(Sym) *sym = NULL;
    if (dladdr1(&_PyRuntime, &info, (void **)&sym, RTLD_DL_SYMENT) && sym)
        out->runtime_size_elf = (long)sym->st_size;
    out->gil_offset = (long)((char *)gil - (char *)&_PyRuntime);
    out->mutex_offset = (long)((char *)&gil->mutex - (char *)gil);
    out->cond_offset = (long)((char *)&gil->cond - (char *)gil);

    PyGILState_STATE g = PyGILState_Ensure();
    PyThreadState *me = PyThreadState_Get();
    out->locked = _Py_atomic_load_relaxed(&gil->locked);
    out->last_holder_is_me = (PyThreadState *)_Py_atomic_load_relaxed(&gil->last_holder) == me;
    out->tstate_current_is_me =
        (PyThreadState *)_Py_atomic_load_relaxed(&_PyRuntime.gilstate.tstate_current) == me;
    out->native_id_ok = me->native_thread_id == (unsigned long)syscall(SYS_gettid);
    out->thread_id_ok = me->thread_id == (unsigned long)pthread_self();
    out->mutex_kind = gil->mutex.__data.__kind;
    out->switch_mutex_kind = gil->switch_mutex.__data.__kind;
    out->cond_wrefs_flags = (int)(gil->cond.__data.__wrefs & 7);
    out->switch_cond_wrefs_flags = (int)(gil->switch_cond.__data.__wrefs & 7);
    PyGILState_Release(g);
    return 0;
}

void cg_dump_py_stack(int fd)
{
    PyThreadState *t = PyGILState_GetThisThreadState();
    if (t)
        _Py_DumpTraceback(fd, t);
}

/* A crashing child's Python stack, raw, for the container to write once it
   has reported the death (crash.c): writing it here, a few small write()s a
   frame, took ~0.23 ms at 25 frames, most of what a report cost.  Follows
   the chain faulthandler's dump follows (CPython 3.11:
   tstate->cframe->current_frame, then _PyInterpreterFrame.previous; the
   offset as _PyInterpreterFrame_LASTI gives it) and reads nothing else. */
int cg_record_py_stack(void **codes, int *lasti, int max, int *more)
{
    PyThreadState *t = PyGILState_GetThisThreadState();
    *more = 0;
    if (!t || !t->cframe)
        return 0;
    int n = 0;
    for (_PyInterpreterFrame *f = t->cframe->current_frame; f; f = f->previous) {
        if (n == max) {
            *more = 1;
            break;
        }
        codes[n] = f->f_code;
        lasti[n] = _PyInterpreterFrame_LASTI(f);
        n++;
    }
    return n;
}

/* The code objects belong to the dead child's frames, which are never
   cleared (core.py: release and abandon leave what they referenced); a
   reference of the container's own makes that not matter. */
void cg_hold_py_stack(void *const *codes, int n, int hold)
{
    PyGILState_STATE g = PyGILState_Ensure();
    for (int i = 0; i < n; i++) {
        if (hold)
            Py_INCREF((PyObject *)codes[i]);
        else
            Py_DECREF((PyObject *)codes[i]);
    }
    PyGILState_Release(g);
}

static void put_pystr(struct ss_buf *o, PyObject *str)
{
    Py_ssize_t n = 0;
    const char *s = PyUnicode_Check(str) ? PyUnicode_AsUTF8AndSize(str, &n) : NULL;
    if (s) {
        ss_mem(o, s, (size_t)n);
    } else {
        PyErr_Clear();
        ss_str(o, "???");
    }
}

/* One line a frame, as faulthandler writes them ("  File "f", line N in
   name"), innermost first. */
int cg_frame_text(void *code_, int lasti, char *buf, int size)
{
    PyGILState_STATE g = PyGILState_Ensure();
    PyCodeObject *code = (PyCodeObject *)code_;
    struct ss_buf o = {buf, (size_t)size - 1, 0};
    put_pystr(&o, code->co_name);
    ss_str(&o, " (");
    put_pystr(&o, code->co_filename);
    ss_str(&o, ":");
    ss_dec(&o, PyCode_Addr2Line(code, lasti * (int)sizeof(_Py_CODEUNIT)));
    ss_str(&o, ")");
    ss_cstr(&o);
    PyGILState_Release(g);
    return (int)o.n;
}

void cg_write_py_stack(void *const *codes, const int *lasti, int n, int more, int fd)
{
    PyGILState_STATE g = PyGILState_Ensure();
    for (int i = 0; i < n; i++) {
        PyCodeObject *code = (PyCodeObject *)codes[i];
        char line[1024];
        struct ss_buf o = {line, sizeof line - 1, 0};
        ss_str(&o, "  File \"");
        put_pystr(&o, code->co_filename);
        ss_str(&o, "\", line ");
        ss_dec(&o, PyCode_Addr2Line(code, lasti[i] * (int)sizeof(_Py_CODEUNIT)));
        ss_str(&o, " in ");
        put_pystr(&o, code->co_name);
        ss_str(&o, "\n");
        if (o.n == o.cap)
            line[o.n - 1] = '\n';
        if (ss_write_all(fd, line, o.n) < 0)
            break;
    }
    if (more)
        ss_write_all(fd, "  ...\n", 6);
    PyGILState_Release(g);
}
