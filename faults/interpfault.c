/* interpfault.c - die half-way through changing CPython 3.11's interpreter
 * state, as a node process SIGKILLed at that instruction would (tests of
 * container/isolated/clonecore/interp.c and pyalloc.c).  A test extension of the rig,
 * like gilfault.c: the product's C has no test entry points.
 *
 * Each function is called through cffi (which releases the GIL around the
 * call), takes the GIL, leaves the state it names half-done, and SIGKILLs
 * its own process holding the GIL.  Compiled with Py_BUILD_CORE against the
 * running interpreter's headers, whose layout the product's start-up check
 * (assumptions.py) vouches for. */
#define Py_BUILD_CORE 1
#include <Python.h>
#include "internal/pycore_interp.h" /* the collector's generations */
#include "internal/pycore_frame.h"  /* _PyInterpreterFrame.localsplus */

#include <dlfcn.h>
#include <signal.h>
#include <string.h>
#include <sys/syscall.h>
#include <time.h>
#include <ucontext.h>
#include <unistd.h>

#include "interpfault.h"

#define AS_GC(o) ((PyGC_Head *)(o)-1)

static _Noreturn void die(void)
{
    kill(getpid(), SIGKILL);
    for (;;)
        pause();
}

static PyGC_Head *young(void)
{
    return &PyInterpreterState_Main()->gc.generations[0].head;
}

/* A list, tracked, at the young generation's tail: then the first `stores`
   of the four stores that untrack it (_PyObject_GC_UNTRACK, in its order:
   prev's next, next's prev, its own next, its flags), with a second list
   after it so that its next is an object, not the head. */
int interpfault_die_mid_gc_untrack(int stores)
{
    PyGILState_Ensure();
    PyObject *victim = PyList_New(0);
    PyObject *after = PyList_New(0);
    (void)after;
    PyGC_Head *gc = AS_GC(victim);
    PyGC_Head *prev = _PyGCHead_PREV(gc), *next = _PyGCHead_NEXT(gc);
    if (stores >= 1)
        _PyGCHead_SET_NEXT(prev, next);
    if (stores >= 2)
        _PyGCHead_SET_PREV(next, prev);
    if (stores >= 3)
        gc->_gc_next = 0;
    die();
}

/* A list made untracked, then the first `stores` of the four stores that
   track it at the young generation's tail (_PyObject_GC_TRACK, in its
   order: the tail's next, its prev, its next, the head's prev). */
int interpfault_die_mid_gc_track(int stores)
{
    PyGILState_Ensure();
    PyObject *victim = PyList_New(0);
    PyObject_GC_UnTrack(victim);
    PyGC_Head *gc = AS_GC(victim), *head = young();
    PyGC_Head *last = (PyGC_Head *)head->_gc_prev;
    if (stores >= 1)
        _PyGCHead_SET_NEXT(last, gc);
    if (stores >= 2)
        _PyGCHead_SET_PREV(gc, last);
    if (stores >= 3)
        _PyGCHead_SET_NEXT(gc, head);
    die();
}

/* `list` (the caller's, one it made) one item longer, its new item not
   stored yet: as list_resize leaves it before PyList_SET_ITEM.  The slot
   holds a pointer nothing may follow. */
int interpfault_die_mid_list_append(void *list)
{
    PyGILState_Ensure();
    PyListObject *l = (PyListObject *)list;
    if (PyList_Append((PyObject *)l, Py_None) < 0) /* room for one more, then undo */
        return -1;
    Py_SET_SIZE(l, Py_SIZE(l) - 1);
    l->ob_item[Py_SIZE(l)] = (PyObject *)(uintptr_t)0x13;
    Py_SET_SIZE(l, Py_SIZE(l) + 1);
    die();
}

/* The calling Python frame's locals made what a frame being pushed or
   cleared holds when its task is killed there: pointers at memory never
   written (a small integer, an address with nothing mapped, one into a
   mapping that holds no object), then death holding the GIL. */
int interpfault_die_with_torn_locals(void)
{
    PyGILState_Ensure();
    _PyInterpreterFrame *f = PyThreadState_Get()->cframe->current_frame;
    static const uintptr_t torn[] = {0x23, 0x200000221, 8};
    for (int i = 0; i < f->f_code->co_nlocalsplus; i++)
        f->localsplus[i] = (PyObject *)torn[i % 3];
    die();
}

/* Allocate Python objects (pymalloc-sized) until a timer tick lands on an
   instruction inside the library whose path contains `library` (the
   allocator guard, whose pyalloc.c serves them), then die right there, from
   the signal handler.  Ticks every `period_us` of this thread's CPU time.
   Returns only if it never landed there within `max_ticks` ticks. */
static const char *g_library;
static volatile long g_ticks;

static void on_tick(int sig, siginfo_t *si, void *uc_)
{
    (void)sig, (void)si;
    ucontext_t *uc = uc_;
    Dl_info info;
    g_ticks++;
    void *pc = (void *)uc->uc_mcontext.gregs[REG_RIP];
    if (dladdr(pc, &info) && info.dli_fname && strstr(info.dli_fname, g_library))
        syscall(SYS_tgkill, getpid(), syscall(SYS_gettid), SIGKILL);
}

int interpfault_die_inside(const char *library, int period_us, long max_ticks)
{
    g_library = library;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_sigaction = on_tick;
    sa.sa_flags = SA_SIGINFO | SA_RESTART;
    sigaction(SIGPROF, &sa, NULL);
    struct sigevent sev;
    memset(&sev, 0, sizeof sev);
    sev.sigev_notify = SIGEV_THREAD_ID;
    sev.sigev_signo = SIGPROF;
    sev._sigev_un._tid = (pid_t)syscall(SYS_gettid);
    timer_t t;
    if (timer_create(CLOCK_THREAD_CPUTIME_ID, &sev, &t) != 0)
        return -1;
    struct itimerspec its = {{0, period_us * 1000L}, {0, period_us * 1000L}};
    timer_settime(t, 0, &its, NULL);
    PyGILState_STATE g = PyGILState_Ensure();
    while (g_ticks < max_ticks) {
        PyObject *keep = PyList_New(0);
        for (int i = 0; i < 64; i++) {
            PyObject *o = PyTuple_New(i % 8 + 1);
            if (!o || PyList_Append(keep, o) < 0)
                break;
            Py_DECREF(o);
        }
        Py_DECREF(keep);
    }
    timer_delete(t);
    PyGILState_Release(g);
    return 0;
}
