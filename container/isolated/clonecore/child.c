/*
 * child.c - a child: how it is born (the clone3 trampoline, on the monitor
 * thread) and what it runs on its own stack and TLS before and after its
 * Python target (child_main).
 *
 * A "child" is a task made with clone3(CLONE_VM) and no CLONE_THREAD: its own
 * pid, signal dispositions and rlimits, but the container's address space.
 * glibc knows nothing of such a task; contexts.c gave it a TLS block with a
 * struct pthread in it, cg_spawn a stack; child_main gives it the rest of
 * what pthread_create would have: a robust-futex list, a locale, a resolver
 * state, signal handlers.  It leaves with a raw SYS_exit.
 */
#include "core.h"
#include "child.h"
#include "clonecore.h"
#include "contexts.h"
#include "crash.h"
#include "monitor.h"

#include <errno.h>
#include <linux/futex.h> /* struct robust_list_head */
#include <linux/sched.h> /* struct clone_args, CLONE_INTO_CGROUP, ... */
#include <locale.h>
#include <signal.h>
#include <stdio.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

/* Which child the current task is.  initial-exec so the SIGTERM handler
   reads it with a plain %fs-relative load (no __tls_get_addr, no malloc);
   the static TLS block is part of every _dl_allocate_tls. */
static __thread struct cg_child *cg_self __attribute__((tls_model("initial-exec")));

/* ---------------------------------------------------------------------- */
/* The clone3 trampoline.
 *
 *   long cg_clone3(struct clone_args *args, size_t size,
 *                  int (*fn)(void *), void *arg);
 *
 * The child comes back from the syscall on its new stack (the kernel sets
 * rsp = stack + stack_size, page aligned, hence 16-byte aligned for the call)
 * with every register but rax/rcx/r11 as the parent had them.  So fn and arg
 * travel in r8/r9.  The child must not return into the parent's frame: it
 * calls fn and ends with a raw SYS_exit, which ends only this task and runs
 * no atexit handler and no stdio flush in the shared address space.
 */
long cg_clone3(struct clone_args *args, size_t size, int (*fn)(void *), void *arg);
__asm__(".text\n"
        ".p2align 4\n"
        ".type cg_clone3, @function\n"
        "cg_clone3:\n"
        "    mov %rdx, %r8\n" /* fn  */
        "    mov %rcx, %r9\n" /* arg */
        "    mov $"
        "435"
        ", %eax\n" /* SYS_clone3 (x86_64) */
        "    syscall\n"
        "    test %rax, %rax\n"
        "    jnz 1f\n"         /* parent (pid) or error (-errno) */
        "    xor %ebp, %ebp\n" /* child: outermost frame */
        "    mov %r9, %rdi\n"
        "    call *%r8\n"
        "    mov %eax, %edi\n"
        "    mov $60, %eax\n" /* SYS_exit */
        "    syscall\n"
        "    hlt\n"
        "1:  ret\n"
        ".size cg_clone3, .-cg_clone3\n");
_Static_assert(SYS_clone3 == 435, "SYS_clone3 number used in the trampoline");

/* ---------------------------------------------------------------------- */
/* The child.                                                              */

/* SIGTERM and SIGINT (Ctrl-C signals the whole foreground process group,
   children included): set the stop flag once, remember which signal, wake
   the monitor.  A process-directed signal can land on any thread of the
   child, including threads it created, whose cg_self is NULL: those pass it
   on to the child's main task (tid == pid). */
static void on_stop_signal(int sig)
{
    int saved = errno;
    struct cg_child *c = cg_self;
    if (!c) {
        syscall(SYS_tgkill, getpid(), getpid(), sig);
    } else {
        int zero = 0, none = CG_STOP_NONE;
        __atomic_compare_exchange_n(&c->stop_signal, &zero, sig, false, __ATOMIC_SEQ_CST,
                                    __ATOMIC_SEQ_CST);
        if (__atomic_compare_exchange_n(&c->stop_requested, &none, CG_STOP_SIGNAL, false,
                                        __ATOMIC_SEQ_CST, __ATOMIC_SEQ_CST)) {
            monitor_wake();
        }
        child_gate_post(c, 1); /* we may be waiting at the gate */
    }
    errno = saved;
}

/* jemalloc: an arena of its own for this child (a lock it dies holding in
   malloc then stops only those who free its blocks, not everyone who
   allocates), optionally no thread cache (no blocks sit cached in a dead
   child). */
static void jemalloc_setup(struct cg_child *c)
{
    mallctl_fn mallctl = cg_mallctl();
    c->arena = -1;
    if (!mallctl)
        return;
    if (cg_cfg()->jemalloc_own_arena) {
        unsigned a;
        size_t sz = sizeof a;
        if (mallctl("arenas.create", &a, &sz, NULL, 0) == 0 &&
            mallctl("thread.arena", NULL, NULL, &a, sizeof a) == 0)
            c->arena = (int)a;
    }
    if (!cg_cfg()->jemalloc_tcache) {
        bool off = false;
        mallctl("thread.tcache.enabled", NULL, NULL, &off, sizeof off);
    }
}

static int exit_code_of_current_exception(void) /* GIL held */
{
    if (!PyErr_ExceptionMatches(PyExc_SystemExit)) {
        /* Never PyErr_Print: it sets sys.last_* in the shared interpreter
           and would exit the *container* on SystemExit. */
        PyErr_PrintEx(0);
        return 1;
    }
    PyObject *type, *value, *tb;
    PyErr_Fetch(&type, &value, &tb);
    PyErr_NormalizeException(&type, &value, &tb);
    PyObject *code = value ? PyObject_GetAttrString(value, "code") : NULL;
    int rc = 1;
    if (code == NULL)
        PyErr_Clear();
    else if (code == Py_None)
        rc = 0;
    else if (PyLong_Check(code))
        rc = (int)PyLong_AsLong(code);
    else
        PyObject_Print(code, stderr, Py_PRINT_RAW), fputc('\n', stderr);
    if (PyErr_Occurred())
        PyErr_Clear();
    Py_XDECREF(code);
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(tb);
    return rc;
}

static int child_main(void *arg)
{
    struct cg_child *c = arg;

    /* 1. Core dumps off for this thread group (rlimits are per thread
       group, so the container keeps its own).  A dump would write the whole
       shared address space.  1, not 0: below the minimum dump size for a
       file core_pattern, and the "don't dump" value for a pipe one. */
    if (!(c->flags & CG_FLAG_ALLOW_CORE)) {
        struct rlimit no_core = {1, 1};
        syscall(SYS_prlimit64, 0, RLIMIT_CORE, &no_core, NULL);
    }
    /* 2. The kernel marks robust mutexes we hold as owner-died on our exit
       only if it knows our list.  Must be done by this task itself. */
    syscall(SYS_set_robust_list, c->tcb + cg_tcb_layout()->robust_head,
            sizeof(struct robust_list_head));
    /* 2b. With the allocator guard: threads we create find our slot by pid. */
    if (c->ctx)
        guard_child_start();
    /* 3. Locale: the fresh TLS has no ctype tables; uselocale sets them. */
    uselocale(LC_GLOBAL_LOCALE);
    AT(c->tcb, cg_tcb_layout()->resp_tls, struct __res_state *) = &c->res;
    /* 4. Die with the monitor thread (= the container).  If it is already
       gone we have been reparented: leave. */
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != c->parent_tgid)
        return 127;
    /* ps and top name us "cg-node", not after the monitor thread we were
       cloned from ("cg-monitor"); the host renames us after our node. */
    prctl(PR_SET_NAME, "cg-node");
    /* 5. Graceful stop: our own SIGTERM/SIGINT handler (CLONE_CLEAR_SIGHAND
       left every handler at SIG_DFL); crash reports on a stack of our own;
       the allocator; then unblock what the monitor blocked. */
    cg_self = c;
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_stop_signal;
    sa.sa_flags = SA_RESTART;
    sigemptyset(&sa.sa_mask);
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    if (cg_cfg()->crash_report)
        crash_handlers_install(c);
    if (cg_cfg()->stop_signal)
        stop_requests_take(cg_cfg()->stop_signal);
    if (!c->ctx)
        jemalloc_setup(c);
    sigset_t none;
    sigemptyset(&none);
    sigprocmask(SIG_SETMASK, &none, NULL);

    /* 6. Python, in the thread state the parent made for us (so we never
       take the runtime's HEAD_LOCK, which has no owner to repair): bind it
       to this task, take the GIL, run, clear it and drop the GIL.  release()
       deletes it. */
    __atomic_store_n(&c->py_phase, CG_PY_INSIDE, __ATOMIC_RELEASE);
    cg_tstate_bind(c->tstate);
    PyEval_RestoreThread(c->tstate);
    PyObject *r = PyObject_CallNoArgs(c->target);
    int code = 0;
    if (r)
        Py_DECREF(r);
    else
        code = exit_code_of_current_exception();
    PyThreadState_Clear(c->tstate);
    PyEval_SaveThread();
    __atomic_store_n(&c->py_phase, CG_PY_LEFT, __ATOMIC_RELEASE);
    return code; /* trampoline: SYS_exit(code) */
}

int cg_self_stop_requested(void) /* -1 when not called from a child */
{
    struct cg_child *c = cg_self;
    return c ? __atomic_load_n(&c->stop_requested, __ATOMIC_ACQUIRE) : -1;
}

/* The gate: where a child waits, off the GIL (cffi releases it around the
   call), for its parent's word: the host's spare waits there for the node
   it is to build, and every node's process waits there, once built, until
   the container has announced the load, instead of competing with that for
   the GIL.  The word counts the parent's "go"s (cg_go); each wait takes one,
   so a go that comes before its wait is not lost (FUTEX_WAIT returns at once
   when the word has changed).  A stop request, from the parent or our own
   stop signal, sets CG_GO_STOP, which ends every wait for good.  Private
   futexes work across the children: they are keyed by the address space,
   which they all share.  Returns 1 if it is to stop, 0 if it took a go, -1
   when not called from a child. */
int cg_self_wait_go(void)
{
    struct cg_child *c = cg_self;
    if (!c)
        return -1;
    for (;;) {
        unsigned word = __atomic_load_n(&c->go, __ATOMIC_ACQUIRE);
        if (word & CG_GO_STOP)
            return 1;
        if (word > c->go_taken) {
            c->go_taken++;
            return 0;
        }
        syscall(SYS_futex, &c->go, FUTEX_WAIT_PRIVATE, word, NULL, NULL, 0);
    }
}

/* One more go, or (stop) end every wait. */
void child_gate_post(struct cg_child *c, unsigned stop)
{
    if (stop)
        __atomic_fetch_or(&c->go, CG_GO_STOP, __ATOMIC_RELEASE);
    else
        __atomic_fetch_add(&c->go, 1, __ATOMIC_RELEASE);
    syscall(SYS_futex, &c->go, FUTEX_WAKE_PRIVATE, 1, NULL, NULL, 0);
}

/* On the monitor thread (PR_SET_PDEATHSIG follows the spawning thread):
   clone3 the child onto its stack and TLS, into its cgroup if it has one.
   Its pid, or -errno. */
long child_clone(struct cg_child *c)
{
    struct clone_args a;
    memset(&a, 0, sizeof a);
    a.flags = CLONE_VM | CLONE_FS | CLONE_FILES | CLONE_PIDFD | CLONE_SETTLS | CLONE_CLEAR_SIGHAND |
              CLONE_CHILD_SETTID | CLONE_PARENT_SETTID;
    a.pidfd = (uintptr_t)&c->pidfd;
    a.child_tid = a.parent_tid = (uintptr_t)(c->tcb + cg_tcb_layout()->tid);
    a.exit_signal = SIGCHLD;
    a.stack = (uintptr_t)(c->map + (c->map_len - c->stack_size));
    a.stack_size = c->stack_size;
    a.tls = (uintptr_t)c->tcb;
    if (c->cgroup_fd >= 0) {
        a.flags |= CLONE_INTO_CGROUP;
        a.cgroup = (uint64_t)c->cgroup_fd;
    }
    c->parent_tgid = getpid();
    return cg_clone3(&a, sizeof a, child_main, c);
}
