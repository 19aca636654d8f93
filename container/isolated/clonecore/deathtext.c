/*
 * deathtext.c - the words for a death, as far as the core knows it: the
 * CRASHED event's text (herald.c) and the log's.  Written on the monitor
 * thread, which must not allocate or take a lock a dead node may hold: with
 * sigsafe.h's writer.
 */
#include "core.h"
#include "deathtext.h"
#include "sigsafe.h"

#include <signal.h>
#include <string.h>

/* Names of the CG_REPAIR_* bits, by bit (repair.h). */
static const char *const REPAIR_NAMES[] = {
#define REPAIR_NAME(name, bit) [bit] = #name,
    CG_REPAIRS(REPAIR_NAME)
#undef REPAIR_NAME
};

/* The name of repair bit `bit`, NULL if none. */
const char *cg_repair_name(unsigned bit)
{
    return bit < sizeof REPAIR_NAMES / sizeof *REPAIR_NAMES ? REPAIR_NAMES[bit] : NULL;
}

/* "SIGKILL", or "signal 99" for one without a name. */
static void signal_name(struct ss_buf *o, int sig)
{
    const char *abbrev = sigabbrev_np(sig);
    if (abbrev) {
        ss_str(o, "SIG");
        ss_str(o, abbrev);
    } else {
        ss_str(o, "signal ");
        ss_dec(o, sig);
    }
}

/* What the event and the log say of a death, as far as the core knows it:
   how it ended (code: CLD_*, 0 when someone else reaped it), what the
   monitor repaired, what the allocator guard did with its arena (CG_ALLOC_*
   bits of the record's alloc word), and the outside signal that asked it
   to stop (0: none).  Python adds what it alone knows.  Its length. */
int cg_describe_death(int status, int code, uint32_t repairs, uint32_t alloc, int stop_signal,
                      char *out, int size)
{
    if (size < 1)
        return 0;
    struct ss_buf o = {out, (size_t)size - 1, 0};
    if (code == CLD_KILLED || code == CLD_DUMPED) {
        ss_str(&o, "killed by ");
        signal_name(&o, status);
    } else if (code == 0) {
        ss_str(&o, "exited, status unknown");
    } else {
        ss_str(&o, "exited with code ");
        ss_dec(&o, status);
    }
    if (repairs & ~(uint32_t)CG_REPAIR_GIL_TIMEOUT) {
        const char *sep = "; repaired: ";
        for (unsigned b = 0; b < sizeof REPAIR_NAMES / sizeof *REPAIR_NAMES; b++)
            if (repairs & (1u << b)) {
                ss_str(&o, sep);
                ss_str(&o, REPAIR_NAMES[b]);
                sep = ", ";
            }
    }
    if (alloc & CG_ALLOC_FAULTED)
        ss_str(&o, "; it faulted, so its heap may be torn: its arena is quarantined");
    else if (alloc & CG_ALLOC_QUARANTINED)
        ss_str(&o, "; it died inside the allocator: its arena is quarantined");
    if (alloc & CG_ALLOC_PY_ABANDONED)
        ss_str(&o, "; it died inside Python's object allocator: its pools are abandoned");
    if (stop_signal > 0) {
        ss_str(&o, " after an outside ");
        signal_name(&o, stop_signal);
    }
    ss_cstr(&o);
    return (int)o.n;
}
