"""A stray write from one node into another node's native heap.

Every node process of an isolated container shares one address space: a
wild pointer in one node can reach any other node's memory. The allocator
guard gives each node process heaps of its own; with ``--pkeys`` each heap
is under a memory protection key of its own that no other node process may
write, so the write faults in the writer. Without keys is the baseline,
the way thread mode is for crashes. The victim checks its buffer every
10 ms; a change it finds and the container does not notice is a
``corrupted`` trial.
"""

import pytest

from cloneguard.faults.trials import FAULTS
from cloneguard.harness.plan import DEEP_FLOOR_TRIALS
from cloneguard.harness.rig import TrialOutcome
from cloneguard.harness.skips import heap_keys_missing

# With keys: every wild write into another node's heap caught, the victim
# intact (the floor; quick runs: all 3).
FLOOR = 0.99
needs_keys = pytest.mark.skipif(heap_keys_missing() is not None, reason=f"--pkeys: {heap_keys_missing()}")

FAULT = "wild-write-into-another-nodes-heap"
SHARED = "wild-write-into-shared-memory"


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_without_protection_keys_a_wild_write_corrupts_silently(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault=FAULT,
        profile=profile,
        mitigations={"protection_keys": False},
        claim="baseline: without memory protection keys (--no-pkeys), 64 bytes written by one node into a buffer in "
        "another node's native heap land there, and nothing but the victim notices",
    )
    trials = FAULTS[FAULT](rig_factory(profile, extra_args=("--no-pkeys",)))
    run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.CORRUPTED, at_least=1.0)


@needs_keys
@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_with_protection_keys_a_wild_write_kills_the_writer_alone(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault=FAULT,
        profile=profile,
        mitigations={"protection_keys": True},
        claim="with protection keys (the default wherever the CPU has them), 64 bytes written by one node "
        "into a buffer in another node's native heap fault in the writer: it alone is reported "
        "CRASHED (SIGSEGV, a protection-key violation in the victim's heap) and the victim's buffer "
        "is intact",
    )
    trials = FAULTS[FAULT](rig_factory(profile))  # the default: jemalloc, keyed
    planned = run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=FLOOR if planned >= DEEP_FLOOR_TRIALS else 1.0)


@pytest.mark.parametrize("keys", [pytest.param(True, marks=needs_keys), False], ids=["pkeys", "no-pkeys"])
def test_a_wild_write_into_shared_memory_corrupts_with_keys_or_without(keys, rig_factory, resilience, run_trials):
    resilience.describe(
        fault=SHARED,
        profile="per-node",
        mitigations={"protection_keys": keys},
        claim="measured, not promised: 64 bytes written by one node into another node's Python object "
        "(a 4 KiB bytearray: memory every node writes legitimately, under no key) land there, with "
        "--pkeys or without, and nothing but the victim notices",
    )
    trials = FAULTS[SHARED](rig_factory("per-node", extra_args=() if keys else ("--no-pkeys",)))
    run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.CORRUPTED, at_least=1.0)


TABLES = "wild-write-into-container-state"


@pytest.mark.parametrize("keys", [pytest.param(True, marks=needs_keys), False], ids=["pkeys", "no-pkeys"])
def test_a_wild_write_into_the_containers_state(keys, rig_factory, resilience, run_trials):
    resilience.describe(
        fault=TABLES,
        profile="per-node",
        mitigations={"protection_keys": keys},
        claim=(
            "with protection keys (the default wherever the CPU has them), 64 bytes written by a node "
            "into the container's allocator tables fault in the "
            "writer: it alone is reported CRASHED (SIGSEGV, a protection-key violation in the container's "
            "allocator tables) and the rest goes on"
            if keys
            else "baseline: without memory protection keys (--no-pkeys), 64 bytes written by a node into "
            "the container's "
            "allocator tables land there, and nothing notices"
        ),
    )
    trials = FAULTS[TABLES](rig_factory("per-node", extra_args=() if keys else ("--no-pkeys",)))
    planned = run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    if keys:
        resilience.expect_no_container_death()
        resilience.expect_rate(TrialOutcome.SURVIVED, at_least=FLOOR if planned >= DEEP_FLOOR_TRIALS else 1.0)
    else:
        resilience.expect_rate(TrialOutcome.CORRUPTED, at_least=1.0)
