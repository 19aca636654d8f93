"""A stray write from one node into another node's native heap.

Every node process of an isolated container shares one address space: a
wild pointer in one node can reach any other node's memory. The allocator
guard gives each node process heaps of its own, but nothing yet stops a
write into them: this is the baseline the memory-protection-keys work is
measured against (docs/evidence.md), the way thread mode is for crashes.
The victim checks its buffer every 10 ms; a change it finds and the
container does not notice is a ``corrupted`` trial.
"""

import pytest

from cloneguard.faults.trials import FAULTS
from cloneguard.harness.rig import TrialOutcome

FAULT = "wild-write-into-another-nodes-heap"


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_without_protection_keys_a_wild_write_corrupts_silently(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault=FAULT,
        profile=profile,
        mitigations={"protection_keys": False},
        claim="baseline: without memory protection keys, 64 bytes written by one node into a buffer in "
        "another node's native heap land there, and nothing but the victim notices",
    )
    trials = FAULTS[FAULT](rig_factory(profile))
    run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.CORRUPTED, at_least=1.0)
