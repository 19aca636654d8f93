"""A heap overflow inside a node's own heap.

A node overflows one of its own blocks by 4 KiB (over its neighbours and
the allocator's metadata between them) and goes on allocating. The
allocator guard gives every node process arenas of its own, so the damage
should stay in that node: it dies of it, or goes on with its own heap
corrupted, and every other node and the container go on untouched.
"""

import pytest

from cloneguard.faults.trials import FAULTS, MALLOC_ALLOCATORS
from cloneguard.harness.plan import DEEP_FLOOR_TRIALS
from cloneguard.harness.rig import TrialOutcome

FAULT = "heap-overflow-in-own-heap"
FLOOR = 0.99


@pytest.mark.parametrize("allocator", ["glibc", "jemalloc"])
@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_an_overflow_of_a_nodes_own_heap_stays_in_that_node(profile, allocator, rig_factory, resilience, run_trials):
    resilience.describe(
        fault=FAULT,
        profile=profile,
        mitigations={"alloc_guard": True, "allocator": allocator},
        claim="a node that overflows a block of its own heap by 4 KiB and goes on allocating harms "
        "nothing but itself: another node's buffer stays intact, it and the container go on",
    )
    trials = FAULTS[FAULT](rig_factory(profile, extra_args=MALLOC_ALLOCATORS[allocator]))
    planned = run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=FLOOR if planned >= DEEP_FLOOR_TRIALS else 1.0)
