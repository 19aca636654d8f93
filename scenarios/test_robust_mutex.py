"""A node dies holding a lock of the container's (a robust mutex)."""

import pytest

from cloneguard.faults.trials import FAULTS
from cloneguard.harness.plan import DEEP_FLOOR_TRIALS
from cloneguard.harness.rig import TrialOutcome


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_death_holding_a_container_lock_is_repaired(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault="die-holding-robust-mutex",
        profile=profile,
        mitigations={"robust_mutex": True},
        claim="a node that dies holding the container's progress-board lock, its slot "
        "half-written: the next locker gets EOWNERDEAD, repairs the slot, and "
        "everyone goes on",
    )
    fault = FAULTS["die-holding-robust-mutex"](rig_factory(profile))
    deep = run_trials(fault.trial, fault.settle, quick=3, deep=200, rig=fault.rig) >= DEEP_FLOOR_TRIALS
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=FLOOR if deep else QUICK_FLOOR)


# Per-node 399 of 400 over deep-5 and deep-8, shared 400 of 400. deep-8's
# one hang (per-node) was not the mutex: the probe node's process, being
# unloaded, deleted its DDS participant inside rclpy with the GIL held and
# Fast DDS busy-waited there (eProsima/Fast-DDS#6513; docs/evidence.md). A
# quick run's 3 trials allow one such hang (a 0.25% rate fails 3 of 3 once
# in ~130 runs).
FLOOR = 0.99
QUICK_FLOOR = 0.66
