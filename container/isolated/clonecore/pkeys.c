/*
 * pkeys.c - memory protection keys: what this machine has, and the facts
 * about them that per-node heap protection rests on, checked on the calling
 * thread (cg_pkeys_probe, read by pkeys.probe(); the container runs it at
 * start-up with --pkeys and refuses where a fact does not hold: heapkeys.c
 * is the heap protection that rests on them).
 *
 * Intel/AMD protection keys (PKU): every page carries a 4-bit key in its
 * page-table entry (pkey_mprotect sets it); every thread has a 32-bit PKRU
 * register with two bits per key, AD (access disable) and WD (write
 * disable), that it reads and writes itself, unprivileged (RDPKRU/WRPKRU)
 * and no other thread can change.  A write the PKRU forbids faults in the
 * writer (SIGSEGV, si_code SEGV_PKUERR, si_pkey the key).  Key 0 is every
 * page's default; pkey_alloc hands out the others (15 on x86_64), for the
 * whole address space: with CLONE_VM, for every node process at once.
 *
 * What the probe establishes, each a field of struct cg_pkeys_probe:
 *   cpu_pku, os_pke   CPUID.(EAX=7,ECX=0):ECX bits 3 and 4: the CPU has
 *                     PKU, and the kernel turned it on (CR4.PKE)
 *   keys              how many pkey_alloc gives before ENOSPC (all freed)
 *   mprotect_keeps    a later plain mprotect of a tagged page keeps its key
 *                     (the allocators grow their heaps with mprotect)
 *   thread_inherits   a thread made by pthread_create starts with its
 *                     creator's PKRU (the threads a node process makes,
 *                     Fast DDS's, get the node's rights)
 *   write_faults      a write the PKRU forbids never lands (checked with
 *                     the fault taken on a thread of the probe's own, whose
 *                     handler sees SEGV_PKUERR and the key)
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE /* pkey_alloc, pkey_mprotect, pkey_set */
#endif
#include <errno.h>
#include <pthread.h>
#include <setjmp.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cpuid.h>

#include "core.h"
#include "pkeys.h"
#include "contexts.h"

#ifndef SEGV_PKUERR
#define SEGV_PKUERR 4
#endif

static uint32_t read_pkru(void)
{
    uint32_t eax, edx;
    __asm__ volatile(".byte 0x0f, 0x01, 0xee" : "=a"(eax), "=d"(edx) : "c"(0)); /* RDPKRU */
    return eax;
}

/* The key of the mapping that holds addr, from /proc/self/smaps; -1 if not
   found. */
static int key_of(const void *addr)
{
    FILE *f = fopen("/proc/self/smaps", "re");
    if (!f)
        return -1;
    char line[512];
    int in = 0, key = -1;
    uintptr_t a = (uintptr_t)addr;
    while (fgets(line, sizeof line, f)) {
        unsigned long lo, hi;
        if (sscanf(line, "%lx-%lx ", &lo, &hi) == 2) { /* a mapping's first line */
            if (in)
                break;
            in = a >= lo && a < hi;
        } else if (in && sscanf(line, "ProtectionKey: %d", &key) == 1) {
            break;
        }
    }
    fclose(f);
    return key;
}

struct inherit_arg {
    uint32_t pkru;
};

static void *report_pkru(void *p)
{
    ((struct inherit_arg *)p)->pkru = read_pkru();
    return NULL;
}

/* The faulting write, on a thread of its own with a handler of its own. */
static __thread sigjmp_buf t_fault_jmp;
static __thread volatile int t_fault_code, t_fault_key;

static void on_fault(int sig, siginfo_t *si, void *uc)
{
    (void)sig, (void)uc;
    t_fault_code = si->si_code;
    t_fault_key = si->si_pkey;
    siglongjmp(t_fault_jmp, 1);
}

struct write_arg {
    volatile char *page;
    int key;
    int landed, code, fault_key;
};

static void *forbidden_write(void *p)
{
    struct write_arg *w = p;
    t_fault_code = t_fault_key = -1;
    pkey_set(w->key, PKEY_DISABLE_WRITE);
    if (sigsetjmp(t_fault_jmp, 1) == 0)
        w->page[0] = 2;
    pkey_set(w->key, 0);
    w->landed = w->page[0] == 2;
    w->code = t_fault_code;
    w->fault_key = t_fault_key;
    return NULL;
}

static int probe_write_faults(volatile char *page, int key)
{
    /* The handler is the process's for a moment (run the probe before
       anything else can fault); what was there is put back. */
    struct sigaction sa = {0}, old;
    sa.sa_sigaction = on_fault;
    sa.sa_flags = SA_SIGINFO;
    sigemptyset(&sa.sa_mask);
    if (sigaction(SIGSEGV, &sa, &old) != 0)
        return -1;
    struct write_arg w = {page, key, 0, -1, -1};
    pthread_t t;
    int ok = -1;
    if (pthread_create(&t, NULL, forbidden_write, &w) == 0) {
        pthread_join(t, NULL);
        ok = !w.landed && w.code == SEGV_PKUERR && w.fault_key == key;
    }
    sigaction(SIGSEGV, &old, NULL);
    return ok;
}

int cg_pkeys_probe(struct cg_pkeys_probe *out)
{
    memset(out, 0, sizeof *out);
    out->mprotect_keeps = out->thread_inherits = out->write_faults = -1;
    unsigned a, b, c, d;
    if (__get_cpuid_count(7, 0, &a, &b, &c, &d)) {
        out->cpu_pku = (c >> 3) & 1;
        out->os_pke = (c >> 4) & 1;
    }
    if (!out->os_pke)
        return 0;
    out->pkru = read_pkru();

    /* With heap protection on, the allocator guard holds every key: the
       probe borrows its last one (no node process exists yet). */
    int keys[16], n = cg_pkeys_in_use(keys, 16), borrowed = n > 0;
    if (!borrowed) {
        n = 0;
        while (n < 16) {
            int k = pkey_alloc(0, 0);
            if (k < 0) {
                out->alloc_errno = errno;
                break;
            }
            keys[n++] = k;
        }
    }
    out->keys = n;
    int key = n ? keys[borrowed ? n - 1 : 0] : -1;
    for (int i = 1; i < n && !borrowed; i++)
        pkey_free(keys[i]);
    if (key < 0)
        return 0;

    long pg = sysconf(_SC_PAGESIZE);
    char *page = mmap(NULL, pg, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
    if (page != MAP_FAILED) {
        if (pkey_mprotect(page, pg, PROT_READ | PROT_WRITE, key) == 0 && key_of(page) == key) {
            page[0] = 1;
            out->mprotect_keeps =
                mprotect(page, pg, PROT_READ | PROT_WRITE) == 0 && key_of(page) == key;
            /* Inheritance: a PKRU unlike the default (writes to the probe
               key disabled), then a thread. */
            pkey_set(key, PKEY_DISABLE_WRITE);
            uint32_t mine = read_pkru();
            struct inherit_arg arg = {~mine};
            pthread_t t;
            if (pthread_create(&t, NULL, report_pkru, &arg) == 0) {
                pthread_join(t, NULL);
                out->thread_inherits = arg.pkru == mine;
            }
            pkey_set(key, 0);
            out->write_faults = probe_write_faults(page, key);
        }
        munmap(page, pg);
    }
    if (!borrowed)
        pkey_free(key);
    return 0;
}
