"""A double free, by one node, of a block another node malloc'd.

The allocator guard hands a block freed by anyone but its owner back to the
owner (allocguard.c), which frees it at its next malloc. Freed twice in a
row, the block would be handed back twice: the owner would free it twice
(its arena corrupted) or follow a hand-over stack linked to itself forever,
holding the GIL. The guard marks a handed-back block and aborts whoever
frees it again before the owner freed it (a small block is held until the
owner's next take-back): the faulty node dies, the owner goes on.
"""

import pytest

from cloneguard.faults.trials import FAULTS, MALLOC_ALLOCATORS
from cloneguard.harness.plan import DEEP_FLOOR_TRIALS
from cloneguard.harness.rig import TrialOutcome

FAULT = "double-free-of-another-nodes-block"
# Every double free caught: the owner frees a small block it took back only
# at its next take-back (deep: 99%).
FLOOR = 0.99


@pytest.mark.parametrize("allocator", ["glibc", "jemalloc"])
@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_a_double_free_of_another_nodes_block_kills_the_freer_alone(
    profile, allocator, rig_factory, resilience, run_trials
):
    resilience.describe(
        fault=FAULT,
        profile=profile,
        mitigations={"alloc_guard": True, "allocator": allocator},
        claim="a node that frees another node's 64-byte block twice in a row is reported CRASHED "
        "(SIGABRT, the allocator guard's double-free check) and the block's owner goes on, its "
        "heap intact",
    )
    trials = FAULTS[FAULT](rig_factory(profile, extra_args=MALLOC_ALLOCATORS[allocator]))
    planned = run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=FLOOR if planned >= DEEP_FLOOR_TRIALS else 1.0)
