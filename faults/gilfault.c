/* gilfault.c - die at a chosen point inside CPython 3.11's GIL machinery, as
 * a clone child SIGKILLed there would (tests of the GIL repair in
 * container/isolated/clonecore/gilrepair.c).  A test extension of the rig: the
 * product's C has no test entry points.
 *
 * Reads the GIL's internal state (Python/ceval_gil.h) like gilrepair.c, so
 * it is compiled with Py_BUILD_CORE against the running interpreter's
 * headers; the product's start-up self-check (assumptions.py) is what
 * vouches for that layout. */
#define Py_BUILD_CORE 1
#include <Python.h>
#include "internal/pycore_runtime.h" /* _PyRuntime, _gil_runtime_state */
#include "internal/pycore_pystate.h" /* _PyThreadState_Swap */
#include "internal/pycore_interp.h"  /* struct _ceval_state */

#include <errno.h>
#include <pthread.h>
#include <signal.h>
#include <time.h>
#include <unistd.h>

#include "gilfault.h"

#define GIL (&_PyRuntime.ceval.gil)

static void sleep_us(long us)
{
    struct timespec ts = {us / 1000000, (us % 1000000) * 1000};
    nanosleep(&ts, NULL);
}

/* Make the calling child die (SIGKILL to itself) at `where`.  Called
   through cffi, which has released the GIL around the call. */
int gilfault_die_in_gil(int where)
{
    struct _gil_runtime_state *gil = GIL;
    PyGILState_STATE g = PyGILState_Ensure();
    (void)g;
    switch (where) {
    case GILFAULT_DROP_GIL_LOCKED: /* drop_gil: mutex taken, GIL ours */
        pthread_mutex_lock(&gil->mutex);
        break;
    case GILFAULT_TAKE_GIL_HANDOVER: /* take_gil's hand-over: both mutexes,
                                        locked = 1, last_holder not yet us */
        PyEval_SaveThread();
        for (;;) {
            pthread_mutex_lock(&gil->mutex);
            if (!_Py_atomic_load_relaxed(&gil->locked))
                break;
            /* Ask for it, as take_gil does after a timed-out wait
               (SET_GIL_DROP_REQUEST): else a holder nobody else asks
               (the container's counter thread, the test's main thread
               parked in core.wait) keeps it, and this child lives on past
               the test's wait (seen: 2 runs of the file in 30). */
            struct _ceval_state *ceval2 = &PyInterpreterState_Main()->ceval;
            _Py_atomic_store_relaxed(&ceval2->gil_drop_request, 1);
            _Py_atomic_store_relaxed(&ceval2->eval_breaker, 1);
            pthread_mutex_unlock(&gil->mutex);
            sleep_us(1000);
        }
        pthread_mutex_lock(&gil->switch_mutex);
        _Py_atomic_store_relaxed(&gil->locked, 1);
        break;
    case GILFAULT_TAKE_GIL_CHECKING: /* take_gil: mutex taken, GIL not ours */
        PyEval_SaveThread();
        pthread_mutex_lock(&gil->mutex);
        break;
    case GILFAULT_DROP_GIL_SIGNALLING: { /* drop_gil, inside pthread_cond_signal
                                           (gil->cond): the GIL let go, the
                                           mutex and the condvar's internal
                                           lock held */
        /* As PyEval_SaveThread and drop_gil do it: tstate_current swapped
           to NULL first (left set, the next taker of the GIL dies of
           "orphan tstate" instead), last_holder = us, then under the mutex
           locked = 0 and the signal. */
        PyThreadState *me = _PyThreadState_Swap(&_PyRuntime.gilstate, NULL);
        _Py_atomic_store_relaxed(&gil->last_holder, (uintptr_t)me);
        pthread_mutex_lock(&gil->mutex);
        _Py_atomic_store_relaxed(&gil->locked, 0);
        /* __condvar_acquire_lock: low 2 bits of __g1_orig_size 0 -> 1,
           after any live holder (a waiter cancelling after its timeout
           holds it for a few instructions, without the mutex) let go. */
        unsigned *w = &gil->cond.__data.__g1_orig_size;
        unsigned s = __atomic_load_n(w, __ATOMIC_RELAXED);
        while ((s & 3) != 0 ||
               !__atomic_compare_exchange_n(w, &s, s | 1, true, __ATOMIC_ACQUIRE, __ATOMIC_RELAXED))
            if ((s & 3) != 0) {
                sleep_us(10);
                s = __atomic_load_n(w, __ATOMIC_RELAXED);
            }
        break;
    }
    case GILFAULT_SWITCH_MUTEX: /* drop_gil: switch_mutex taken */
        PyEval_SaveThread();
        pthread_mutex_lock(&gil->switch_mutex);
        break;
    default:
        return -EINVAL;
    }
    kill(getpid(), SIGKILL);
    for (;;)
        pause();
}
