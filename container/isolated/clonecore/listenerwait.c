/*
 * listenerwait.c - Fast DDS's participant listener wait made to sleep.
 *
 * Before a DDS participant is deleted, rmw_fastrtps (and Fast DDS itself, in
 * DomainParticipantImpl::disable) calls DomainParticipant::set_listener(
 * nullptr), which waits for in-flight participant-listener callbacks to end,
 * with its default infinite timeout.  Fast DDS 2.14 turns that timeout into a
 * deadline of time_point::max() on system_clock; libstdc++'s
 * condition_variable::wait_until converts it to its own clock by adding it
 * to now(), the sum overflows, and every wait returns at once: the caller
 * spins, re-taking the mutex the callback needs to finish (its exit takes
 * it), and that callback's thread, woken only to find it taken again, can
 * starve for ever (eProsima/Fast-DDS#6513).  In this container that is a
 * node's process stuck in its teardown (a failed load never answered) or,
 * when rclpy deletes the participant holding the GIL, every thread.
 *
 * The remedy: every overload of set_listener ends in one,
 *     set_listener(DomainParticipantListener*, const StatusMask&,
 *                  std::chrono::seconds timeout),
 * which libfastrtps calls through its own PLT.  Its slot in libfastrtps's
 * GOT is pointed at finite_set_listener below, which turns an infinite wait
 * into finite ones (a real sleep on the condition variable) until one
 * succeeds: the same meaning, without the spin.  Every node process shares
 * this address space, so one store covers all of them.
 *
 * Assumptions (each checked by cg_bound_listener_wait, which changes nothing
 * when one fails and says which):
 *   - the library is libfastrtps.so.2.* (measured on 2.14.5), loaded;
 *   - x86-64 SysV calls: this, listener, &mask in rdi/rsi/rdx, the timeout
 *     (one int64_t of seconds) in rcx, ReturnCode_t (one uint32_t) in eax;
 *     OK is 0, and a wait that timed out returns non-zero after its timeout;
 *   - that overload has an R_X86_64_JUMP_SLOT relocation in libfastrtps,
 *     and dlsym finds its definition inside libfastrtps;
 *   - it is installed before any participant is deleted (the container's
 *     start-up): a lazy binding of the slot running at the same moment
 *     could write the real address back over ours.
 */
#ifndef _GNU_SOURCE
#define _GNU_SOURCE /* dl_iterate_phdr, RTLD_NOLOAD */
#endif
#include <dlfcn.h>
#include <elf.h>
#include <errno.h>
#include <link.h>
#include <pthread.h>
#include <stdio.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

#include "core.h"
#include "listenerwait.h"

#undef p_type /* <resolv.h> (core.h) renames it to __p_type; here it is ElfW(Phdr)'s */

#define FASTRTPS_SONAME "libfastrtps.so.2."
#define SET_LISTENER_3                                                                             \
    "_ZN8eprosima7fastdds3dds17DomainParticipant12set_listenerEPNS1_25DomainParticipantListener"   \
    "ERKNS1_10StatusMaskENSt6chrono8durationIlSt5ratioILl1ELl1EEEE"
#define INFINITE_S INT64_MAX /* std::chrono::seconds::max() */
#define STEP_S 1             /* each finite wait */

typedef uint32_t (*set_listener_fn)(void *self, void *listener, const void *mask,
                                    int64_t timeout_s);

static set_listener_fn g_real; /* the definition in libfastrtps */
static uintptr_t *g_slot;      /* libfastrtps's GOT slot for it */
static long g_bounded;         /* infinite waits made finite, ever */

static uint32_t finite_set_listener(void *self, void *listener, const void *mask, int64_t timeout_s)
{
    if (timeout_s != INFINITE_S)
        return g_real(self, listener, mask, timeout_s);
    __atomic_add_fetch(&g_bounded, 1, __ATOMIC_RELAXED);
    for (;;) {
        int64_t start = cg_mono_ns();
        uint32_t rc = g_real(self, listener, mask, STEP_S);
        /* Non-zero soon after the call: not a timeout, an answer. */
        if (rc == 0 || cg_mono_ns() - start < STEP_S * 500000000LL)
            return rc;
    }
}

struct found {
    const char *why; /* set when a check failed */
    char name[256];
    uintptr_t base, lo, hi; /* load bias, extent of its loaded segments */
    uintptr_t slot;         /* address of the JUMP_SLOT word */
    uintptr_t relro_lo, relro_hi;
};

/* A d_ptr of the in-memory dynamic section: glibc relocates them in place on
 * x86-64; a value below the load bias is still a link-time address. */
static uintptr_t dyn_ptr(uintptr_t base, uintptr_t p)
{
    return p < base ? p + base : p;
}

static void find_slot(struct dl_phdr_info *info, struct found *f)
{
    const ElfW(Dyn) *dyn = NULL;
    for (int i = 0; i < info->dlpi_phnum; i++) {
        const ElfW(Phdr) *ph = &info->dlpi_phdr[i];
        uintptr_t start = info->dlpi_addr + ph->p_vaddr;
        if (ph->p_type == PT_DYNAMIC)
            dyn = (const ElfW(Dyn) *)start;
        else if (ph->p_type == PT_GNU_RELRO) {
            f->relro_lo = start;
            f->relro_hi = start + ph->p_memsz;
        } else if (ph->p_type == PT_LOAD) {
            if (!f->lo || start < f->lo)
                f->lo = start;
            if (start + ph->p_memsz > f->hi)
                f->hi = start + ph->p_memsz;
        }
    }
    if (!dyn) {
        f->why = "libfastrtps has no dynamic section";
        return;
    }
    uintptr_t base = info->dlpi_addr, jmprel = 0, symtab = 0, strtab = 0;
    size_t pltrelsz = 0;
    int pltrel = 0;
    for (; dyn->d_tag != DT_NULL; dyn++) {
        switch (dyn->d_tag) {
        case DT_JMPREL:
            jmprel = dyn_ptr(base, dyn->d_un.d_ptr);
            break;
        case DT_PLTRELSZ:
            pltrelsz = dyn->d_un.d_val;
            break;
        case DT_PLTREL:
            pltrel = (int)dyn->d_un.d_val;
            break;
        case DT_SYMTAB:
            symtab = dyn_ptr(base, dyn->d_un.d_ptr);
            break;
        case DT_STRTAB:
            strtab = dyn_ptr(base, dyn->d_un.d_ptr);
            break;
        }
    }
    if (!jmprel || !symtab || !strtab || pltrel != DT_RELA) {
        f->why = "libfastrtps has no RELA PLT relocations";
        return;
    }
    const ElfW(Rela) *r = (const ElfW(Rela) *)jmprel;
    const ElfW(Sym) *syms = (const ElfW(Sym) *)symtab;
    for (size_t i = 0; i < pltrelsz / sizeof *r; i++) {
        if (ELF64_R_TYPE(r[i].r_info) != R_X86_64_JUMP_SLOT)
            continue;
        const char *name = (const char *)strtab + syms[ELF64_R_SYM(r[i].r_info)].st_name;
        if (strcmp(name, SET_LISTENER_3) == 0) {
            f->slot = base + r[i].r_offset;
            return;
        }
    }
    f->why = "libfastrtps calls DomainParticipant::set_listener(listener, mask, timeout) without a "
             "PLT slot";
}

static int visit(struct dl_phdr_info *info, size_t size, void *arg)
{
    (void)size;
    struct found *f = arg;
    const char *base = strrchr(info->dlpi_name, '/');
    base = base ? base + 1 : info->dlpi_name;
    if (strncmp(base, FASTRTPS_SONAME, strlen(FASTRTPS_SONAME)) != 0)
        return 0;
    snprintf(f->name, sizeof f->name, "%s", info->dlpi_name);
    f->base = info->dlpi_addr;
    find_slot(info, f);
    return 1;
}

/* 1: installed (or already); 0: libfastrtps is not loaded (nothing to do);
 * -1: a check failed, nothing changed, why in why_out. */
int cg_bound_listener_wait(char *why_out, int why_size)
{
    static pthread_mutex_t once = PTHREAD_MUTEX_INITIALIZER;
    int rc = 1;
    pthread_mutex_lock(&once);
    if (g_slot)
        goto out;
    struct found f = {0};
    if (!dl_iterate_phdr(visit, &f)) {
        rc = 0;
        goto out;
    }
    if (f.why) {
        snprintf(why_out, why_size, "%s", f.why);
        rc = -1;
        goto out;
    }
    void *h = dlopen(f.name, RTLD_NOW | RTLD_NOLOAD);
    void *real = h ? dlsym(h, SET_LISTENER_3) : NULL;
    if (h)
        dlclose(h);
    if (!real || (uintptr_t)real < f.lo || (uintptr_t)real >= f.hi) {
        snprintf(why_out, why_size,
                 "DomainParticipant::set_listener(listener, mask, timeout) is not defined in %s",
                 f.name);
        rc = -1;
        goto out;
    }
    g_real = (set_listener_fn)real;
    long page = sysconf(_SC_PAGESIZE);
    void *first = (void *)(f.slot & ~(uintptr_t)(page - 1));
    int relro = f.slot >= f.relro_lo && f.slot < f.relro_hi;
    if (relro && mprotect(first, (size_t)page, PROT_READ | PROT_WRITE) != 0) {
        snprintf(why_out, why_size, "cannot make libfastrtps's GOT writable: %s", strerror(errno));
        rc = -1;
        goto out;
    }
    /* One aligned 8-byte store: a concurrent caller jumps through the old
     * target (a lazy-binding stub or the real function) or the new one. */
    __atomic_store_n((uintptr_t *)f.slot, (uintptr_t)finite_set_listener, __ATOMIC_SEQ_CST);
    if (relro)
        mprotect(first, (size_t)page, PROT_READ);
    g_slot = (uintptr_t *)f.slot;
out:
    pthread_mutex_unlock(&once);
    return rc;
}

/* For tests: -1 when libfastrtps's slot does not point here (now), else
 * how many infinite waits have been made finite so far. */
long cg_listener_waits_bounded(void)
{
    if (!g_slot || __atomic_load_n(g_slot, __ATOMIC_SEQ_CST) != (uintptr_t)finite_set_listener)
        return -1;
    return __atomic_load_n(&g_bounded, __ATOMIC_RELAXED);
}
