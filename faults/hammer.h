/* hammer.h - what hammer.c offers (faults/_build_hammer.py feeds these
   declarations to cffi as its cdef). */
#ifndef CLONEGUARD_FAULTS_HAMMER_H
#define CLONEGUARD_FAULTS_HAMMER_H

#include <stddef.h>
#include <stdint.h>

int hammer_run(int ring, uint64_t seed);
long drain_some(int ring);
uint64_t hammer_ops_done(int ring);
void hammer_burst(uint64_t seed, long pairs);
int64_t hammer_pairs(size_t size, long n);
int64_t hammer_copy_pairs(size_t size, long n, int stack);
int64_t hammer_alloc_many(void **out, size_t size, long n);
int64_t hammer_free_many(void **blocks, long n);

#endif
