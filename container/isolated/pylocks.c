/*
 * pylocks.c - Python's lock types for an isolated container: CPython 3.11's
 * _thread.lock and _thread.RLock, with the same behaviour, that also know
 * which process holds them.
 *
 * Every node process of an isolated container runs in the container's one
 * interpreter, so every Python lock (threading.Lock, RLock, Condition,
 * queue.Queue, logging's handler locks, importlib's module locks) is shared
 * by all of them.  CPython's lock is a semaphore with no owner: a node
 * process that died holding one left it held, and whoever waited for it
 * waited for ever, with nothing to say why.  These locks record their
 * holder, and a waiter takes over one whose holder's process is known dead.
 *
 * The lock: a futex word (0 free, 1 held, 2 held with waiters: the classic
 * three-state futex mutex) and `holder`, the acquirer's (process id << 32 |
 * thread id), written right after the word is taken and cleared right
 * before it is given back: holder 0 with the word taken is a task inside
 * that window (a death there leaves a lock nobody can be sure of: never
 * taken over, reported).  A Lock may be released by any thread (CPython's
 * rule), which clears holder the same way.
 *
 * Dead processes: the container tells this module of every node process
 * that died without being stopped (node_died) and forgets a pid when a new
 * process gets it (node_born).  A blocked acquire waits in slices of
 * SLICE_MS off the GIL; after each it looks whether the holder's process is
 * one of the dead, and if so takes the lock over with one CAS on `holder`
 * (one waiter wins; the word stays taken, now by it).  Then, holding the
 * GIL, it calls the repair hook (container/isolated/locks.py: it names the
 * lock, records the repair, calls the component's own callback).
 *
 * Installed in place of _thread.allocate_lock and _thread.RLock before
 * threading is first imported (boot.py), so every lock the interpreter's
 * Python code makes is one of these.  CPython's own C-level locks (the GIL,
 * the import lock, HEAD_LOCK) are not Python objects and are not covered.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>

#include <dlfcn.h>
#include <errno.h>
#include <linux/futex.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdint.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include "allocguard/allocguard.h"

#define SLICE_MS 100  /* a blocked acquire looks at its holder this often */
#define STUCK_MS 1000 /* ... and says so once if none is known after this */
#define NDEAD 4096    /* dead node processes remembered */

/* ---------------------------------------------------------------------- */
/* Dead node processes.                                                    */

static _Atomic int g_dead[NDEAD]; /* pids, 0: a free entry */
static _Atomic unsigned g_dead_next;
static _Atomic int g_any_dead;  /* has any node process died yet? */
static PyObject *g_repair_hook; /* hook(lock, pid, tid) */
static PyObject *g_stuck_hook;  /* hook(lock, waited_s) */

static int is_dead(int pid)
{
    if (pid <= 0 || !atomic_load_explicit(&g_any_dead, memory_order_acquire))
        return 0;
    for (int i = 0; i < NDEAD; i++)
        if (atomic_load_explicit(&g_dead[i], memory_order_relaxed) == pid)
            return 1;
    return 0;
}

/* ---------------------------------------------------------------------- */
/* The lock word and its holder.                                           */

struct core {
    _Atomic uint32_t word;
    _Atomic uint64_t holder; /* pid << 32 | tid, 0: none known */
};

/* The calling task, as a holder: pid << 32 | tid.  getpid() and gettid()
   are two system calls, about as long as the rest of an acquire and
   release, so each thread keeps the value.  A kept value is used only while
   (a) the tid glibc keeps in the thread's descriptor (written by the kernel
   at clone) is still the one it was kept for: a node process's main task
   reusing a context's TLS block has a new tid, and its pid is its tid;
   (b) no node process has died since it was kept: a killed thread's TLS
   block can be handed to a new thread (once something joins it), whose
   tid the kernel could make the same only after pid_max others;
   (c) its thread has not ended: a pthread key's destructor empties it, as
   glibc hands an ended thread's stack and TLS to a later thread.
   Without the descriptor's tid (module_exec could not find or check it)
   every acquire asks the kernel. */
static long g_tid_offset = -1;    /* tid's offset in struct pthread */
static _Atomic unsigned g_deaths; /* node_died calls so far */
static pthread_key_t g_me_key;
static __thread uint64_t t_me;
static __thread unsigned t_me_deaths;

static inline int descriptor_tid(void)
{
    return *(volatile int *)((char *)pthread_self() + g_tid_offset);
}

static void forget_me(void *unused)
{
    (void)unused;
    t_me = 0;
}

static uint64_t me_slow(void)
{
    return (uint64_t)(uint32_t)getpid() << 32 | (uint32_t)syscall(SYS_gettid);
}

static inline uint64_t me(void)
{
    if (g_tid_offset < 0)
        return me_slow();
    unsigned deaths = atomic_load_explicit(&g_deaths, memory_order_acquire);
    if (t_me && t_me_deaths == deaths && (uint32_t)descriptor_tid() == (uint32_t)t_me)
        return t_me;
    uint64_t v = me_slow();
    if ((uint32_t)descriptor_tid() != (uint32_t)v)
        return v; /* a task whose descriptor is not its own: never kept */
    t_me = v;
    t_me_deaths = deaths;
    pthread_setspecific(g_me_key, (void *)1); /* so that forget_me runs at its end */
    return v;
}

/* Where glibc keeps a thread's tid (its debugger descriptor, as
   assumptions.py reads it), checked on the calling thread; -1 if not. */
static long find_tid_offset(void)
{
    const uint32_t *d = dlvsym(RTLD_DEFAULT, "_thread_db_pthread_tid", "GLIBC_PRIVATE");
    if (!d || d[0] != 32 || d[1] != 1)
        return -1;
    long off = (long)d[2];
    if (*(int *)((char *)pthread_self() + off) != (int)syscall(SYS_gettid))
        return -1;
    return off;
}

static long futex(_Atomic uint32_t *w, int op, uint32_t val, const struct timespec *ts)
{
    return syscall(SYS_futex, w, op | FUTEX_PRIVATE_FLAG, val, ts, NULL, 0);
}

static inline int try_take(struct core *c)
{
    uint32_t zero = 0;
    if (!atomic_compare_exchange_strong_explicit(&c->word, &zero, 1, memory_order_acquire,
                                                 memory_order_relaxed))
        return 0;
    atomic_store_explicit(&c->holder, me(), memory_order_release);
    return 1;
}

static void give_back(struct core *c)
{
    atomic_store_explicit(&c->holder, 0, memory_order_release);
    if (atomic_exchange_explicit(&c->word, 0, memory_order_release) == 2)
        futex(&c->word, FUTEX_WAKE, 1, NULL);
}

enum { GOT, TIMED_OUT, INTERRUPTED, TOOK_OVER, STUCK };

static int64_t now_ns(void)
{
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return now.tv_sec * 1000000000LL + now.tv_nsec;
}

/* Without the GIL: wait for the word until `deadline` (monotonic ns, -1:
   none), in slices; GOT, TOOK_OVER (*dead: its holder, whose process is
   dead), TIMED_OUT, INTERRUPTED (a signal: the caller runs handlers), or
   STUCK once *stuck_at (monotonic ns) has passed with no holder known
   after a node death (a holder that died between taking the word and
   recording itself: nobody can tell it from a live one in that window). */
static int wait_word(struct core *c, int64_t deadline, uint64_t *dead, int64_t *stuck_at)
{
    for (;;) {
        if (atomic_exchange_explicit(&c->word, 2, memory_order_acquire) == 0) {
            atomic_store_explicit(&c->holder, me(), memory_order_release);
            return GOT;
        }
        uint64_t h = atomic_load_explicit(&c->holder, memory_order_acquire);
        if (h && is_dead((int)(h >> 32)) && atomic_compare_exchange_strong(&c->holder, &h, me())) {
            *dead = h;
            return TOOK_OVER;
        }
        int64_t slice = (int64_t)SLICE_MS * 1000000, t = now_ns();
        if (*stuck_at >= 0 && t >= *stuck_at && !h && atomic_load(&g_any_dead)) {
            *stuck_at = -1; /* said once */
            return STUCK;
        }
        if (deadline >= 0) {
            int64_t left = deadline - t;
            if (left <= 0)
                return TIMED_OUT;
            if (left < slice)
                slice = left;
        }
        struct timespec ts = {slice / 1000000000, slice % 1000000000};
        if (futex(&c->word, FUTEX_WAIT, 2, &ts) < 0 && errno == EINTR)
            return INTERRUPTED;
    }
}

/* acquire(blocking=True, timeout=-1) arguments, as CPython 3.11 reads them:
 *timeout is -1 (forever), 0 (try) or a relative time in ns. */
static int parse_acquire(PyObject *args, PyObject *kwds, _PyTime_t *timeout)
{
    static char *kwlist[] = {"blocking", "timeout", NULL};
    int blocking = 1;
    PyObject *obj = NULL;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "|pO:acquire", kwlist, &blocking, &obj))
        return -1;
    const _PyTime_t unset = _PyTime_FromSeconds(-1);
    *timeout = unset;
    if (obj && _PyTime_FromSecondsObject(timeout, obj, _PyTime_ROUND_TIMEOUT) < 0)
        return -1;
    if (!blocking && *timeout != unset) {
        PyErr_SetString(PyExc_ValueError, "can't specify a timeout for a non-blocking call");
        return -1;
    }
    if (*timeout < 0 && *timeout != unset) {
        PyErr_SetString(PyExc_ValueError, "timeout value must be positive");
        return -1;
    }
    if (!blocking) {
        *timeout = 0;
    } else if (*timeout != unset) {
        _PyTime_t us = _PyTime_AsMicroseconds(*timeout, _PyTime_ROUND_TIMEOUT);
        if (us > PY_TIMEOUT_MAX) {
            PyErr_SetString(PyExc_OverflowError, "timeout value is too large");
            return -1;
        }
    } else {
        *timeout = -1;
    }
    return 0;
}

/* After a takeover, once the new holder's own state is set: the hook,
   holding the GIL (it may name the lock, record the repair, call the
   component's callback). */
static void report_takeover(PyObject *lock, uint64_t dead)
{
    if (!g_repair_hook)
        return;
    PyObject *res = PyObject_CallFunction(g_repair_hook, "OiI", lock, (int)(dead >> 32),
                                          (unsigned)(dead & 0xffffffffu));
    if (res)
        Py_DECREF(res);
    else
        PyErr_WriteUnraisable(g_repair_hook);
}

/* 1 acquired, 0 not, -1 an exception (from a signal handler).  Takes the
   GIL back before returning.  *dead: the holder whose process was dead, if
   it was taken over (then the caller reports it), else 0. */
static int take_core(PyObject *lock, struct core *c, _PyTime_t timeout, uint64_t *dead)
{
    *dead = 0;
    if (try_take(c))
        return 1;
    if (timeout == 0)
        return 0;
    int64_t start = now_ns(), deadline = timeout > 0 ? start + (int64_t)timeout : -1;
    int64_t stuck_at = start + (int64_t)STUCK_MS * 1000000;
    for (;;) {
        int r;
        Py_BEGIN_ALLOW_THREADS r = wait_word(c, deadline, dead, &stuck_at);
        Py_END_ALLOW_THREADS if (r == GOT || r == TOOK_OVER) return 1;
        if (r == TIMED_OUT)
            return 0;
        if (r == STUCK) {
            if (g_stuck_hook) {
                PyObject *res =
                    PyObject_CallFunction(g_stuck_hook, "Od", lock, (now_ns() - start) / 1e9);
                if (res)
                    Py_DECREF(res);
                else
                    PyErr_WriteUnraisable(g_stuck_hook);
            }
            continue;
        }
        if (Py_MakePendingCalls() < 0) /* INTERRUPTED: run the handlers */
            return -1;
    }
}

/* The allocator guard's stop point for "a Python lock just acquired"
   (stops.c, the test rig's seam): its armed flag, one load an acquire, and
   the call when armed.  NULL without the guard.  A request may name one
   lock by a key (stops.c): whether the lock just taken is that one is
   Python's to say (locks.py's name hook, set_name_hook), called with the
   GIL and the lock held; a hook that takes a lock itself meets this check
   again and is not called again (g_in_name_hook, guarded by the GIL). */
static _Atomic int *g_stops_armed;
static void (*g_stop_here)(int place);
static int64_t (*g_stop_lock_key)(void);
static PyObject *g_name_hook; /* hook(lock, key) -> bool */
static int g_in_name_hook;

static int is_the_lock_asked_for(PyObject *lock)
{
    int64_t key = g_stop_lock_key ? g_stop_lock_key() : 0;
    if (key <= 0)
        return key == 0; /* any lock; -1: no such request here */
    if (!g_name_hook || g_in_name_hook)
        return 0;
    g_in_name_hook = 1;
    PyObject *res = PyObject_CallFunction(g_name_hook, "OL", lock, (long long)key);
    g_in_name_hook = 0;
    int yes = res != NULL && PyObject_IsTrue(res) == 1;
    if (!res)
        PyErr_WriteUnraisable(g_name_hook);
    Py_XDECREF(res);
    return yes;
}

static int acquire_core(PyObject *lock, struct core *c, _PyTime_t timeout, uint64_t *dead)
{
    int r = take_core(lock, c, timeout, dead);
    if (r == 1 && g_stops_armed && atomic_load_explicit(g_stops_armed, memory_order_relaxed) &&
        is_the_lock_asked_for(lock))
        g_stop_here(CGA_STOP_PY_LOCK);
    return r;
}

/* ---------------------------------------------------------------------- */
/* lock                                                                    */

typedef struct {
    PyObject_HEAD struct core c;
    PyObject *weakrefs;
} LockObject;

static PyObject *lock_acquire(LockObject *self, PyObject *args, PyObject *kwds)
{
    _PyTime_t timeout;
    if (parse_acquire(args, kwds, &timeout) < 0)
        return NULL;
    uint64_t dead;
    int r = acquire_core((PyObject *)self, &self->c, timeout, &dead);
    if (r < 0)
        return NULL;
    if (dead)
        report_takeover((PyObject *)self, dead);
    return PyBool_FromLong(r);
}

static PyObject *lock_release(LockObject *self, PyObject *unused)
{
    (void)unused;
    if (atomic_load(&self->c.word) == 0) {
        PyErr_SetString(PyExc_RuntimeError, "release unlocked lock");
        return NULL;
    }
    give_back(&self->c);
    Py_RETURN_NONE;
}

static PyObject *lock_exit(LockObject *self, PyObject *args)
{
    (void)args;
    return lock_release(self, NULL);
}

static PyObject *lock_locked(LockObject *self, PyObject *unused)
{
    (void)unused;
    return PyBool_FromLong(atomic_load(&self->c.word) != 0);
}

static PyObject *lock_at_fork_reinit(LockObject *self, PyObject *unused)
{
    (void)unused;
    atomic_store(&self->c.word, 0);
    atomic_store(&self->c.holder, 0);
    Py_RETURN_NONE;
}

static PyObject *holder_of(struct core *c)
{
    uint64_t h = atomic_load(&c->holder);
    if (!h)
        Py_RETURN_NONE;
    return Py_BuildValue("(iI)", (int)(h >> 32), (unsigned)(h & 0xffffffffu));
}

static PyObject *lock_holder(LockObject *self, void *unused)
{
    (void)unused;
    return holder_of(&self->c);
}

static PyObject *lock_repr(LockObject *self)
{
    return PyUnicode_FromFormat("<%s %s object at %p>",
                                atomic_load(&self->c.word) ? "locked" : "unlocked",
                                _PyType_Name(Py_TYPE(self)), self);
}

static void lock_dealloc(LockObject *self)
{
    PyObject_GC_UnTrack(self);
    if (self->weakrefs)
        PyObject_ClearWeakRefs((PyObject *)self);
    PyTypeObject *tp = Py_TYPE(self);
    tp->tp_free(self);
    Py_DECREF(tp);
}

static int lock_traverse(LockObject *self, visitproc visit, void *arg)
{
    Py_VISIT(Py_TYPE(self));
    return 0;
}

static PyMethodDef lock_methods[] = {
    {"acquire_lock", (PyCFunction)(void (*)(void))lock_acquire, METH_VARARGS | METH_KEYWORDS, NULL},
    {"acquire", (PyCFunction)(void (*)(void))lock_acquire, METH_VARARGS | METH_KEYWORDS,
     "acquire(blocking=True, timeout=-1) -> bool: as _thread.lock's"},
    {"release_lock", (PyCFunction)lock_release, METH_NOARGS, NULL},
    {"release", (PyCFunction)lock_release, METH_NOARGS, "release(): as _thread.lock's"},
    {"locked_lock", (PyCFunction)lock_locked, METH_NOARGS, NULL},
    {"locked", (PyCFunction)lock_locked, METH_NOARGS, "locked() -> bool"},
    {"__enter__", (PyCFunction)(void (*)(void))lock_acquire, METH_VARARGS | METH_KEYWORDS, NULL},
    {"__exit__", (PyCFunction)lock_exit, METH_VARARGS, NULL},
    {"_at_fork_reinit", (PyCFunction)lock_at_fork_reinit, METH_NOARGS, NULL},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef lock_getset[] = {
    {"holder", (getter)lock_holder, NULL, "(pid, tid) of its last acquirer while held, else None",
     NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyMemberDef lock_members[] = {
    {"__weaklistoffset__", T_PYSSIZET, offsetof(LockObject, weakrefs), READONLY, NULL},
    {NULL, 0, 0, 0, NULL},
};

static PyType_Slot lock_slots[] = {
    {Py_tp_dealloc, lock_dealloc},
    {Py_tp_repr, lock_repr},
    {Py_tp_methods, lock_methods},
    {Py_tp_getset, lock_getset},
    {Py_tp_members, lock_members},
    {Py_tp_traverse, lock_traverse},
    {0, NULL},
};

static PyType_Spec lock_spec = {
    .name = "cloneguard.container.isolated._pylocks.lock",
    .basicsize = sizeof(LockObject),
    .flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_DISALLOW_INSTANTIATION |
             Py_TPFLAGS_IMMUTABLETYPE,
    .slots = lock_slots,
};

static PyTypeObject *g_lock_type;

static PyObject *allocate_lock(PyObject *module, PyObject *unused)
{
    (void)module, (void)unused;
    LockObject *self = PyObject_GC_New(LockObject, g_lock_type);
    if (!self)
        return NULL;
    atomic_init(&self->c.word, 0);
    atomic_init(&self->c.holder, 0);
    self->weakrefs = NULL;
    PyObject_GC_Track(self);
    return (PyObject *)self;
}

/* ---------------------------------------------------------------------- */
/* RLock                                                                   */

typedef struct {
    PyObject_HEAD struct core c;
    unsigned long owner; /* thread ident, as CPython's */
    unsigned long count;
    PyObject *weakrefs;
} RLockObject;

static PyObject *rlock_new(PyTypeObject *type, PyObject *args, PyObject *kwds)
{
    (void)args, (void)kwds;
    RLockObject *self = (RLockObject *)type->tp_alloc(type, 0);
    if (!self)
        return NULL;
    atomic_init(&self->c.word, 0);
    atomic_init(&self->c.holder, 0);
    self->owner = 0;
    self->count = 0;
    self->weakrefs = NULL;
    return (PyObject *)self;
}

static PyObject *rlock_acquire(RLockObject *self, PyObject *args, PyObject *kwds)
{
    _PyTime_t timeout;
    if (parse_acquire(args, kwds, &timeout) < 0)
        return NULL;
    unsigned long tid = PyThread_get_thread_ident();
    if (self->count > 0 && tid == self->owner) {
        unsigned long count = self->count + 1;
        if (count <= self->count) {
            PyErr_SetString(PyExc_OverflowError, "Internal lock count overflowed");
            return NULL;
        }
        self->count = count;
        Py_RETURN_TRUE;
    }
    uint64_t dead;
    int r = acquire_core((PyObject *)self, &self->c, timeout, &dead);
    if (r < 0)
        return NULL;
    if (r) {
        self->owner = tid; /* after a takeover: once, whatever the dead one's count */
        self->count = 1;
    }
    if (dead)
        report_takeover((PyObject *)self, dead);
    return PyBool_FromLong(r);
}

static PyObject *rlock_release(RLockObject *self, PyObject *unused)
{
    (void)unused;
    unsigned long tid = PyThread_get_thread_ident();
    if (self->count == 0 || self->owner != tid) {
        PyErr_SetString(PyExc_RuntimeError, "cannot release un-acquired lock");
        return NULL;
    }
    if (--self->count == 0) {
        self->owner = 0;
        give_back(&self->c);
    }
    Py_RETURN_NONE;
}

static PyObject *rlock_exit(RLockObject *self, PyObject *args)
{
    (void)args;
    return rlock_release(self, NULL);
}

static PyObject *rlock_acquire_restore(RLockObject *self, PyObject *args)
{
    unsigned long owner, count;
    if (!PyArg_ParseTuple(args, "(kk):_acquire_restore", &count, &owner))
        return NULL;
    uint64_t dead;
    if (acquire_core((PyObject *)self, &self->c, -1, &dead) < 0)
        return NULL;
    self->owner = owner;
    self->count = count;
    if (dead)
        report_takeover((PyObject *)self, dead);
    Py_RETURN_NONE;
}

static PyObject *rlock_release_save(RLockObject *self, PyObject *unused)
{
    (void)unused;
    if (self->count == 0) {
        PyErr_SetString(PyExc_RuntimeError, "cannot release un-acquired lock");
        return NULL;
    }
    unsigned long owner = self->owner, count = self->count;
    self->count = 0;
    self->owner = 0;
    give_back(&self->c);
    return Py_BuildValue("kk", count, owner);
}

static PyObject *rlock_recursion_count(RLockObject *self, PyObject *unused)
{
    (void)unused;
    unsigned long tid = PyThread_get_thread_ident();
    return PyLong_FromUnsignedLong(self->owner == tid ? self->count : 0UL);
}

static PyObject *rlock_is_owned(RLockObject *self, PyObject *unused)
{
    (void)unused;
    unsigned long tid = PyThread_get_thread_ident();
    return PyBool_FromLong(self->count > 0 && self->owner == tid);
}

static PyObject *rlock_at_fork_reinit(RLockObject *self, PyObject *unused)
{
    (void)unused;
    atomic_store(&self->c.word, 0);
    atomic_store(&self->c.holder, 0);
    self->owner = 0;
    self->count = 0;
    Py_RETURN_NONE;
}

static PyObject *rlock_holder(RLockObject *self, void *unused)
{
    (void)unused;
    return holder_of(&self->c);
}

static PyObject *rlock_repr(RLockObject *self)
{
    return PyUnicode_FromFormat("<%s %s object owner=%lu count=%lu at %p>",
                                self->count ? "locked" : "unlocked", _PyType_Name(Py_TYPE(self)),
                                self->owner, self->count, self);
}

static void rlock_dealloc(RLockObject *self)
{
    PyObject_GC_UnTrack(self);
    if (self->weakrefs)
        PyObject_ClearWeakRefs((PyObject *)self);
    PyTypeObject *tp = Py_TYPE(self);
    tp->tp_free(self);
    Py_DECREF(tp);
}

static int rlock_traverse(RLockObject *self, visitproc visit, void *arg)
{
    Py_VISIT(Py_TYPE(self));
    return 0;
}

static PyMethodDef rlock_methods[] = {
    {"acquire", (PyCFunction)(void (*)(void))rlock_acquire, METH_VARARGS | METH_KEYWORDS,
     "acquire(blocking=True, timeout=-1) -> bool: as _thread.RLock's"},
    {"release", (PyCFunction)rlock_release, METH_NOARGS, "release(): as _thread.RLock's"},
    {"_is_owned", (PyCFunction)rlock_is_owned, METH_NOARGS, NULL},
    {"_recursion_count", (PyCFunction)rlock_recursion_count, METH_NOARGS, NULL},
    {"_acquire_restore", (PyCFunction)rlock_acquire_restore, METH_VARARGS, NULL},
    {"_release_save", (PyCFunction)rlock_release_save, METH_NOARGS, NULL},
    {"__enter__", (PyCFunction)(void (*)(void))rlock_acquire, METH_VARARGS | METH_KEYWORDS, NULL},
    {"__exit__", (PyCFunction)rlock_exit, METH_VARARGS, NULL},
    {"_at_fork_reinit", (PyCFunction)rlock_at_fork_reinit, METH_NOARGS, NULL},
    {NULL, NULL, 0, NULL},
};

static PyGetSetDef rlock_getset[] = {
    {"holder", (getter)rlock_holder, NULL, "(pid, tid) of its holder while held, else None", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

static PyMemberDef rlock_members[] = {
    {"__weaklistoffset__", T_PYSSIZET, offsetof(RLockObject, weakrefs), READONLY, NULL},
    {NULL, 0, 0, 0, NULL},
};

static PyType_Slot rlock_slots[] = {
    {Py_tp_new, rlock_new},           {Py_tp_dealloc, rlock_dealloc},
    {Py_tp_repr, rlock_repr},         {Py_tp_methods, rlock_methods},
    {Py_tp_getset, rlock_getset},     {Py_tp_members, rlock_members},
    {Py_tp_traverse, rlock_traverse}, {0, NULL},
};

static PyType_Spec rlock_spec = {
    .name = "cloneguard.container.isolated._pylocks.RLock",
    .basicsize = sizeof(RLockObject),
    .flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC | Py_TPFLAGS_IMMUTABLETYPE,
    .slots = rlock_slots,
};

/* ---------------------------------------------------------------------- */
/* The module: the container's side.                                       */

static PyObject *node_died(PyObject *module, PyObject *arg)
{
    (void)module;
    int pid = _PyLong_AsInt(arg);
    if (pid == -1 && PyErr_Occurred())
        return NULL;
    unsigned i = atomic_fetch_add(&g_dead_next, 1) % NDEAD;
    atomic_store(&g_dead[i], pid);
    atomic_store_explicit(&g_any_dead, 1, memory_order_release);
    atomic_fetch_add_explicit(&g_deaths, 1, memory_order_release); /* me(): (b) */
    Py_RETURN_NONE;
}

static PyObject *node_born(PyObject *module, PyObject *arg)
{
    (void)module;
    int pid = _PyLong_AsInt(arg);
    if (pid == -1 && PyErr_Occurred())
        return NULL;
    for (int i = 0; i < NDEAD; i++) {
        int was = pid;
        atomic_compare_exchange_strong(&g_dead[i], &was, 0);
    }
    Py_RETURN_NONE;
}

static PyObject *set_hooks(PyObject *module, PyObject *args)
{
    (void)module;
    PyObject *repair, *stuck, *named = Py_None;
    if (!PyArg_ParseTuple(args, "OO|O:set_hooks", &repair, &stuck, &named))
        return NULL;
    repair = repair == Py_None ? NULL : repair;
    stuck = stuck == Py_None ? NULL : stuck;
    named = named == Py_None ? NULL : named;
    Py_XINCREF(repair);
    Py_XINCREF(stuck);
    Py_XINCREF(named);
    Py_XSETREF(g_repair_hook, repair);
    Py_XSETREF(g_stuck_hook, stuck);
    Py_XSETREF(g_name_hook, named);
    Py_RETURN_NONE;
}

static PyMethodDef module_methods[] = {
    {"allocate_lock", allocate_lock, METH_NOARGS, "a new lock (as _thread.allocate_lock)"},
    {"node_died", node_died, METH_O, "node_died(pid): a node process died without being stopped"},
    {"node_born", node_born, METH_O, "node_born(pid): a new node process has that pid"},
    {"set_hooks", set_hooks, METH_VARARGS,
     "set_hooks(repair, stuck, named=None): repair(lock, pid, tid) after a lock whose holder's "
     "process died "
     "is taken over; stuck(lock, waited_s) once a waiter has waited STUCK_MS with no holder known "
     "after a "
     "death; named(lock, key) -> bool: is this the lock a stop request names by key"},
    {NULL, NULL, 0, NULL},
};

static int module_exec(PyObject *m)
{
    _Atomic int *(*armed_flag)(void) =
        (_Atomic int *(*)(void))dlsym(RTLD_DEFAULT, "cga_stops_armed_flag");
    g_stop_here = (void (*)(int))dlsym(RTLD_DEFAULT, "cga_stop_here");
    g_stops_armed = armed_flag && g_stop_here ? armed_flag() : NULL;
    g_stop_lock_key = (int64_t(*)(void))dlsym(RTLD_DEFAULT, "cga_stop_lock_key");
    if (g_tid_offset < 0 && pthread_key_create(&g_me_key, forget_me) == 0)
        g_tid_offset = find_tid_offset();
    g_lock_type = (PyTypeObject *)PyType_FromModuleAndSpec(m, &lock_spec, NULL);
    if (!g_lock_type || PyModule_AddObjectRef(m, "LockType", (PyObject *)g_lock_type) < 0)
        return -1;
    PyObject *rlock = PyType_FromModuleAndSpec(m, &rlock_spec, NULL);
    if (!rlock || PyModule_AddObject(m, "RLock", rlock) < 0)
        return -1;
    if (PyModule_AddIntConstant(m, "STUCK_MS", STUCK_MS) < 0)
        return -1;
    return PyModule_AddIntConstant(m, "SLICE_MS", SLICE_MS);
}

static PyModuleDef_Slot module_slots[] = {
    {Py_mod_exec, module_exec},
    {0, NULL},
};

static struct PyModuleDef module_def = {
    PyModuleDef_HEAD_INIT,
    .m_name = "cloneguard.container.isolated._pylocks",
    .m_doc = "Python's lock types, knowing their holder's process (pylocks.c)",
    .m_size = 0,
    .m_methods = module_methods,
    .m_slots = module_slots,
};

PyMODINIT_FUNC PyInit__pylocks(void); /* no header: Python finds it by name */
PyMODINIT_FUNC PyInit__pylocks(void)
{
    return PyModuleDef_Init(&module_def);
}
