/*
 * memwatch.c - the container's memory watch, on the monitor thread: before
 * the container's memory reaches what it may use, it ends the node process
 * that uses the most.  The kernel's OOM killer would end every process that
 * shares the address space, i.e. the whole container; this ends one node.
 *
 * What it may use, and what it uses, Python found (memory_watch.py) and
 * gave here as open files, read with pread on each look:
 *   a memory cgroup (the one whose limit is nearest): its usage
 *     (v1 memory.usage_in_bytes, v2 memory.current) less its inactive file
 *     cache ("total_inactive_file" / "inactive_file" of memory.stat, read
 *     only near the limit: the kernel reclaims that cache before it kills);
 *   or the machine: MemTotal less MemAvailable (/proc/meminfo).
 * When that use reaches the limit less the margin, the live node process
 * with the highest score gets SIGKILL: its memory in use as the allocator
 * guard counts it, plus its oom_score_adj in thousandths of the limit (as
 * the kernel scores; -1000: never this one).  Its death text says why.
 *
 * How often it looks: after each look it may sleep as long as a node
 * allocating RATE_BYTES_PER_MS would take to use half of what is left
 * before the trigger, from 1 to 100 ms: ten looks a second far from the
 * limit, one a millisecond near it.
 *
 * A dead node's memory stays in the address space (nothing can yet prove
 * that no live task still reaches its blocks), so after an end the use stays
 * near the trigger, wavering about it as caches come and go.  The next end
 * waits until the use has grown by a quarter of the margin past the last
 * (or came down by half the margin first), and none comes while an ended
 * node is not yet reaped: one leak ends one node, not every node in turn.
 */
#include "core.h"
#include "memwatch.h"
#include "contexts.h"
#include "sigsafe.h"

#include <errno.h>
#include <signal.h>
#include <stdlib.h>
#include <string.h>
#include <sys/syscall.h>
#include <unistd.h>

#define RATE_BYTES_PER_MS (4ull << 20) /* 4 GiB/s: a fast leak, paging in */
#define LOOK_MIN_MS 1
#define LOOK_MAX_MS 100

static struct {
    int usage_fd;      /* -1: no watch */
    int stat_fd;       /* memory.stat, -1: none (meminfo) */
    int meminfo;       /* usage_fd is /proc/meminfo */
    char stat_key[32]; /* "total_inactive_file" or "inactive_file" */
    uint64_t limit, margin;
    uint64_t last_end_used; /* the use when it last ended a node, 0: none
                               since memory last came back */
} W = {.usage_fd = -1, .stat_fd = -1};

int cg_memwatch_set(int usage_fd, int stat_fd, const char *stat_key, int meminfo, uint64_t limit,
                    uint64_t margin)
{
    if (usage_fd < 0) { /* off */
        W.usage_fd = W.stat_fd = -1;
        return 0;
    }
    if (!limit || margin >= limit || strlen(stat_key) >= sizeof W.stat_key)
        return -EINVAL;
    W.usage_fd = usage_fd;
    W.stat_fd = stat_fd;
    W.meminfo = meminfo;
    strcpy(W.stat_key, stat_key);
    W.limit = limit;
    W.margin = margin;
    return 0;
}

int cg_child_set_oom_score_adj(struct cg_child *c, int adj)
{
    if (adj < -1000 || adj > 1000)
        return -EINVAL;
    __atomic_store_n(&c->oom_score_adj, adj, __ATOMIC_RELAXED);
    return 0;
}

/* The number after "key" at a line's start in fd's text; -1 if none. */
static int64_t read_field(int fd, const char *key, int64_t unit)
{
    char buf[4096];
    ssize_t n = pread(fd, buf, sizeof buf - 1, 0);
    if (n <= 0)
        return -1;
    buf[n] = '\0';
    size_t k = strlen(key);
    for (char *line = buf; line && *line; line = strchr(line, '\n'), line = line ? line + 1 : NULL)
        if (strncmp(line, key, k) == 0 && (line[k] == ' ' || line[k] == ':'))
            return strtoll(line + k + 1 + (line[k] == ':'), NULL, 10) * unit;
    return -1;
}

/* What the container uses now, in the limit's terms; -1: unreadable. */
static int64_t container_use(bool near)
{
    if (W.meminfo) {
        int64_t avail = read_field(W.usage_fd, "MemAvailable", 1024);
        return avail < 0 ? -1 : (int64_t)W.limit - avail;
    }
    char buf[32];
    ssize_t n = pread(W.usage_fd, buf, sizeof buf - 1, 0);
    if (n <= 0)
        return -1;
    buf[n] = '\0';
    int64_t used = strtoll(buf, NULL, 10);
    if (near && W.stat_fd >= 0) { /* cache the kernel would reclaim first */
        int64_t cache = read_field(W.stat_fd, W.stat_key, 1);
        if (cache > 0)
            used -= cache;
    }
    return used;
}

static int64_t score(struct cg_child *c)
{
    struct cga_slot_memory m;
    int adj = __atomic_load_n(&c->oom_score_adj, __ATOMIC_RELAXED);
    if (adj <= -1000 || cg_child_memory(c, &m) != 0)
        return -1;
    int64_t s = (int64_t)m.in_use + (int64_t)adj * (int64_t)(W.limit / 1000);
    return s > 0 ? s : 0;
}

/* Ends the live node process that scores highest; false if there is none. */
static bool end_biggest(struct cg_child *children, uint64_t used)
{
    struct cg_child *pick = NULL;
    int64_t best = -1;
    for (struct cg_child *c = children; c; c = c->next) {
        int64_t s = score(c);
        if (s > best)
            best = s, pick = c;
    }
    if (!pick)
        return false;
    struct cga_slot_memory m;
    if (cg_child_memory(pick, &m) != 0)
        return false;
    pick->oom_used = used;
    pick->oom_in_use = m.in_use ? m.in_use : 1;
    syscall(SYS_pidfd_send_signal, pick->pidfd, SIGKILL, NULL, 0);
    W.last_end_used = used;
    return true;
}

int memwatch_tick(struct cg_child *children, int sleep_ms)
{
    if (W.usage_fd < 0)
        return sleep_ms;
    uint64_t trigger = W.limit - W.margin;
    int64_t used = container_use(false);
    if (used >= 0 && (uint64_t)used >= trigger)
        used = container_use(true);
    if (used < 0)
        return sleep_ms;
    int look = LOOK_MIN_MS;
    if (W.last_end_used && (uint64_t)used + W.margin / 2 < W.last_end_used)
        W.last_end_used = 0; /* memory came back: a fresh start */
    if ((uint64_t)used < trigger) {
        uint64_t ms = (trigger - (uint64_t)used) / 2 / RATE_BYTES_PER_MS;
        look = ms < LOOK_MIN_MS ? LOOK_MIN_MS : ms > LOOK_MAX_MS ? LOOK_MAX_MS : (int)ms;
    } else {
        bool pending = false;
        for (struct cg_child *c = children; c; c = c->next)
            pending |= c->oom_in_use != 0;
        if (!pending && (!W.last_end_used || (uint64_t)used >= W.last_end_used + W.margin / 4))
            end_biggest(children, (uint64_t)used);
    }
    return sleep_ms < 0 || look < sleep_ms ? look : sleep_ms;
}

/* Child c was ended by the watch: why, at the end of its death text. */
void memwatch_say(const struct cg_child *c, char *text, size_t cap)
{
    struct ss_buf o = {text, cap - 1, strlen(text)};
    if (!c->oom_in_use || o.n >= o.cap)
        return;
    ss_str(&o, "; out of memory: the container used ");
    ss_ratio(&o, c->oom_used, MIB, 1);
    ss_str(&o, " MiB of the ");
    ss_ratio(&o, W.limit, MIB, 1);
    ss_str(&o, " MiB it may use, and this node process the most: ");
    ss_ratio(&o, c->oom_in_use, MIB, 1);
    ss_str(&o, " MiB");
    ss_cstr(&o);
}
