"""A use after free, by one node, of a block another node malloc'd.

A block freed by anyone but its owner goes back to the owner: the
allocator guard links it onto the owner's hand-over stack through its
first word (allocguard.c), and the owner takes it back at its next malloc.
A node that goes on writing the block after freeing it writes the owner's
allocator state (that link) or, once taken back, the owner's next block.
With ``--pkeys`` the block is under its owner's key again as soon as it is
linked, so the write faults in the writer. Without keys is the baseline.
"""

import pytest

from cloneguard.faults.trials import FAULTS
from cloneguard.harness.plan import DEEP_FLOOR_TRIALS
from cloneguard.harness.rig import TrialOutcome
from cloneguard.harness.skips import heap_keys_missing

FAULT = "use-after-free-of-another-nodes-block"
# With keys: every write caught in the writer, the owner intact (deep: 99%).
FLOOR = 0.99


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_without_protection_keys_a_use_after_free_lands_in_the_owner(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault=FAULT,
        profile=profile,
        mitigations={"protection_keys": False},
        claim="baseline: without memory protection keys (--no-pkeys), 64 bytes written by a node into another node's "
        "block it has just freed land in the owner's heap: none of these trials survives",
    )
    trials = FAULTS[FAULT](rig_factory(profile, extra_args=("--no-pkeys",)))
    run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_most=0.0)


@pytest.mark.skipif(heap_keys_missing() is not None, reason=f"--pkeys: {heap_keys_missing()}")
@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_with_protection_keys_a_use_after_free_kills_the_writer_alone(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault=FAULT,
        profile=profile,
        mitigations={"protection_keys": True},
        claim="with protection keys (the default wherever the CPU has them), 64 bytes written by a node "
        "into another node's block it has just freed fault in the writer: it alone is reported "
        "CRASHED (SIGSEGV, a protection-key violation in the owner's heap) and the owner goes on, "
        "its heap intact",
    )
    trials = FAULTS[FAULT](rig_factory(profile))  # the default: jemalloc, keyed
    planned = run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=FLOOR if planned >= DEEP_FLOOR_TRIALS else 1.0)
