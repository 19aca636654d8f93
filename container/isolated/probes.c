/*
 * probes.c - small helpers assumptions.py uses to discover and check the
 * layout the core rests on (the thread pointer, the kernel's robust list,
 * glibc symbols, a live condvar waiter's record), and which allocator the
 * process runs on.  Called from Python at start-up, before any child exists.
 */
#include "core.h"

#include <asm/prctl.h>
#include <dlfcn.h>
#include <errno.h>
#include <pthread.h>
#include <sched.h>
#include <stdio.h>
#include <string.h>
#include <sys/syscall.h>
#include <unistd.h>

uintptr_t cg_thread_pointer(void)
{
    unsigned long fs = 0;
    syscall(SYS_arch_prctl, ARCH_GET_FS, &fs);
    return fs;
}

uintptr_t cg_robust_list_head(void)   /* what the kernel has for this task */
{
    void *head = NULL;
    size_t len = 0;
    if (syscall(SYS_get_robust_list, 0, &head, &len) != 0)
        return 0;
    return (uintptr_t)head;
}

long cg_gettid(void) { return syscall(SYS_gettid); }

void *cg_lookup(const char *name, const char *version)
{
    return version ? dlvsym(RTLD_DEFAULT, name, version)
                   : dlsym(RTLD_DEFAULT, name);
}

long cg_mutex_futex_offset(void)   /* glibc: futex word minus list.__next */
{
    return (long)offsetof(pthread_mutex_t, __data.__lock) -
           (long)offsetof(pthread_mutex_t, __data.__list.__next);
}

int cg_probe_clone3(void)   /* 0 if the kernel has clone3, else errno */
{
    /* A size of 0 is below CLONE_ARGS_SIZE_VER0: EINVAL if clone3 exists. */
    long r = syscall(SYS_clone3, NULL, (size_t)0);
    return (r < 0 && errno == EINVAL) ? 0 : (r < 0 ? errno : EEXIST);
}


struct probe_arg {
    pthread_mutex_t m;
    pthread_cond_t cv;
    int go, ready;
    long cleanup_off;
    char *sp;
    char *volatile tcb;
    void *before, *after;    /* its .cleanup before / after the wait */
};

static void *probe_waiter(void *p)
{
    struct probe_arg *a = p;
    char here;
    a->sp = &here;
    pthread_mutex_lock(&a->m);
    a->tcb = (char *)cg_thread_pointer();
    a->before = *(void **)(a->tcb + a->cleanup_off);
    __atomic_store_n(&a->ready, 1, __ATOMIC_RELEASE);
    while (!a->go)
        pthread_cond_wait(&a->cv, &a->m);
    a->after = *(void **)(a->tcb + a->cleanup_off);
    pthread_mutex_unlock(&a->m);
    return NULL;
}

int cg_probe_condwait(long cleanup_off, struct cg_condwait_probe *out)
{
    memset(out, 0, sizeof *out);
    struct probe_arg a;
    memset(&a, 0, sizeof a);
    a.cleanup_off = cleanup_off;
    pthread_mutex_init(&a.m, NULL);
    pthread_cond_init(&a.cv, NULL);
    pthread_t t;
    if (pthread_create(&t, NULL, probe_waiter, &a) != 0)
        return -EAGAIN;
    while (!__atomic_load_n(&a.ready, __ATOMIC_ACQUIRE))
        sched_yield();
    struct _pthread_cleanup_buffer *buf = NULL;
    for (int i = 0; i < 2000 && (!buf || buf == a.before); i++) {   /* ~2 s */
        buf = __atomic_load_n((struct _pthread_cleanup_buffer **)(a.tcb + cleanup_off),
                              __ATOMIC_ACQUIRE);
        if (!buf || buf == a.before)
            usleep(1000);
    }
    if (buf == a.before)
        buf = NULL;
    if (buf) {
        out->found = 1;
        char *lo = a.sp - 65536, *hi = a.sp + 65536;
        struct cg_cond_cbuf *cb = buf->__arg;
        out->buf_on_stack = (char *)buf > lo && (char *)buf < hi &&
                            (char *)cb > lo && (char *)cb < hi;
        if (out->buf_on_stack) {
            out->routine = (uintptr_t)buf->__routine;
            out->cbuf_matches = cb->cond == &a.cv && cb->mutex == &a.m;
            out->wseq_matches = cb->wseq + 2 == a.cv.__data.__wseq.__value64;
            out->holds_ref = a.cv.__data.__g_refs[cb->wseq & 1] == 2;
            Dl_info info;
            out->routine_in_libc = dladdr((void *)out->routine, &info) &&
                                   info.dli_fname && strstr(info.dli_fname, "libc.so");
        }
    }
    pthread_mutex_lock(&a.m);
    a.go = 1;
    pthread_cond_signal(&a.cv);
    pthread_mutex_unlock(&a.m);
    pthread_join(t, NULL);
    out->cleared_after = out->found && a.after == a.before;
    pthread_cond_destroy(&a.cv);
    pthread_mutex_destroy(&a.m);
    return 0;
}

/* "glibc" or "jemalloc <version>": which malloc the process runs on. */
mallctl_fn find_mallctl(void)
{
    mallctl_fn f = (mallctl_fn)dlsym(RTLD_DEFAULT, "mallctl");
    Dl_info a, b;
    /* jemalloc must be the malloc in use, not merely loaded. */
    if (!f || !dladdr((void *)f, &a) ||
        !dladdr(dlsym(RTLD_DEFAULT, "malloc"), &b) || a.dli_fbase != b.dli_fbase)
        return NULL;
    return f;
}

int cg_allocator(char *buf, size_t len)
{
    mallctl_fn f = find_mallctl();
    const char *v = NULL;
    size_t sz = sizeof v;
    if (f && f("version", &v, &sz, NULL, 0) == 0 && v)
        snprintf(buf, len, "jemalloc %s", v);
    else
        snprintf(buf, len, "glibc");
    return f != NULL;
}

/* Read one jemalloc setting of the calling thread into out (size bytes):
   0, or -1 without jemalloc (or without that setting). */
static int read_mallctl(const char *name, void *out, size_t size)
{
    mallctl_fn f = find_mallctl();
    size_t sz = size;
    return f && f(name, out, &sz, NULL, 0) == 0 ? 0 : -1;
}

/* Whether the calling thread has a jemalloc thread cache: 1/0; -1 without
   jemalloc. */
int cg_jemalloc_thread_tcache(void)
{
    bool on;
    return read_mallctl("thread.tcache.enabled", &on, sizeof on) < 0 ? -1 : on;
}

/* The jemalloc arena the calling thread allocates from; -1 without
   jemalloc. */
int cg_jemalloc_thread_arena(void)
{
    unsigned a;
    return read_mallctl("thread.arena", &a, sizeof a) < 0 ? -1 : (int)a;
}
