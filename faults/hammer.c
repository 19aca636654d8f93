/*
 * The malloc hammer: a fault for "SIGKILL during malloc".
 *
 * hammer_run() allocates and frees blocks of random sizes (16 B .. 1 MiB,
 * log-uniform) as fast as it can, and hands one block in eight to a ring
 * that another node drains and frees, the way a message published by one
 * node is released by another. It never returns: the harness SIGKILLs the
 * process running it at a random instant, very likely inside malloc() or
 * free(), which is the point. Called from Python through cffi, which
 * releases the GIL first, so the death measures the allocator, not the
 * interpreter lock.
 *
 * Rings live in this library's static memory, which every clone child
 * shares; they are single-producer / single-consumer, with C11 atomics.
 */
#include <stdatomic.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "hammer.h"

#define RINGS 8
#define RING_SIZE 4096 /* power of two */

struct ring {
    _Atomic uint64_t head; /* next slot the producer writes */
    _Atomic uint64_t tail; /* next slot the consumer reads */
    void *slot[RING_SIZE];
};

static struct ring rings[RINGS];
static _Atomic uint64_t hammer_ops[RINGS]; /* malloc+free pairs, per ring */

static uint64_t xorshift(uint64_t *s)
{
    uint64_t x = *s;
    x ^= x << 13;
    x ^= x >> 7;
    x ^= x << 17;
    return *s = x;
}

/* 16 B .. 1 MiB, log-uniform: many small blocks, some large ones. */
static size_t random_size(uint64_t *s)
{
    unsigned shift = 4 + (unsigned)(xorshift(s) % 17); /* 2^4 .. 2^20 */
    size_t base = (size_t)1 << shift;
    return base + (size_t)(xorshift(s) % base);
}

static int push(struct ring *r, void *p)
{
    uint64_t head = atomic_load_explicit(&r->head, memory_order_relaxed);
    uint64_t tail = atomic_load_explicit(&r->tail, memory_order_acquire);
    if (head - tail >= RING_SIZE)
        return 0;
    r->slot[head % RING_SIZE] = p;
    atomic_store_explicit(&r->head, head + 1, memory_order_release);
    return 1;
}

int hammer_run(int ring, uint64_t seed)
{
    if (ring < 0 || ring >= RINGS)
        return -1;
    struct ring *r = &rings[ring];
    uint64_t s = seed ? seed : 0x9e3779b97f4a7c15ull;
    for (;;) {
        size_t n = random_size(&s);
        unsigned char *p = malloc(n);
        if (!p)
            continue;
        p[0] = (unsigned char)n; /* touch both ends */
        p[n - 1] = (unsigned char)(n >> 8);
        if (xorshift(&s) % 8 == 0 && push(r, p))
            ; /* handed over: the drain frees it */
        else
            free(p);
        atomic_fetch_add_explicit(&hammer_ops[ring], 1, memory_order_relaxed);
    }
}

/* Malloc/free pairs of 2..64 KiB, for a bounded count: a publisher calls
 * it between messages so that its arena lock is held most of the time,
 * wherever a SIGKILL lands. The sizes are chosen for that: above glibc's
 * per-thread cache (which frees without the lock), below its mmap
 * threshold (which bypasses the arena). */
void hammer_burst(uint64_t seed, long pairs)
{
    uint64_t s = seed ? seed : 0x9e3779b97f4a7c15ull;
    for (long i = 0; i < pairs; i++) {
        size_t n = 2048 + (size_t)(xorshift(&s) % (62 * 1024));
        unsigned char *p = malloc(n);
        if (p) {
            p[0] = (unsigned char)n;
            p[n - 1] = (unsigned char)(n >> 8);
            free(p);
        }
    }
}

/* Free what the ring holds; returns how many blocks. */
long drain_some(int ring)
{
    if (ring < 0 || ring >= RINGS)
        return -1;
    struct ring *r = &rings[ring];
    uint64_t tail = atomic_load_explicit(&r->tail, memory_order_relaxed);
    uint64_t head = atomic_load_explicit(&r->head, memory_order_acquire);
    long freed = 0;
    for (; tail != head; tail++, freed++)
        free(r->slot[tail % RING_SIZE]);
    atomic_store_explicit(&r->tail, tail, memory_order_release);
    return freed;
}

uint64_t hammer_ops_done(int ring)
{
    return (ring < 0 || ring >= RINGS) ? 0 : atomic_load(&hammer_ops[ring]);
}

/* For bench/alloc_guard.py: timed loops, CLOCK_MONOTONIC ns elapsed. */
#include <time.h>

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

/* n malloc(size)/free pairs. */
int64_t hammer_pairs(size_t size, long n)
{
    int64_t t0 = now_ns();
    for (long i = 0; i < n; i++) {
        void *volatile p = malloc(size);
        free(p);
    }
    return now_ns() - t0;
}

/* n blocks of size into out[]; the time it took. */
int64_t hammer_alloc_many(void **out, size_t size, long n)
{
    int64_t t0 = now_ns();
    for (long i = 0; i < n; i++)
        out[i] = malloc(size);
    return now_ns() - t0;
}

/* free() the n blocks of blocks[]; the time it took. */
int64_t hammer_free_many(void **blocks, long n)
{
    int64_t t0 = now_ns();
    for (long i = 0; i < n; i++)
        free(blocks[i]);
    return now_ns() - t0;
}

/* n pairs of a size-byte block filled with size - 1 bytes and freed:
   stack != 0, the C library asks for it itself (strndup: to the allocator
   guard a caller of the stack's, served from the shared arena); stack == 0,
   this code mallocs it and copies the same bytes (the node's own arena).
   size at most 4096. */
int64_t hammer_copy_pairs(size_t size, long n, int stack)
{
    static char text[4096];
    if (size < 1 || size > sizeof text)
        return -1;
    memset(text, 'x', size - 1);
    text[size - 1] = '\0';
    int64_t t0 = now_ns();
    for (long i = 0; i < n; i++) {
        char *volatile p;
        if (stack) {
            p = strndup(text, size - 1);
        } else {
            p = malloc(size);
            memcpy(p, text, size);
        }
        free(p);
    }
    return now_ns() - t0;
}
