"""A node dies holding a lock of the container's (a robust mutex)."""
import pytest

from cloneguard.faults.trials import FAULTS


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_death_holding_a_container_lock_is_repaired(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault="die-holding-robust-mutex", profile=profile, mitigations={"robust_mutex": True},
        claim="a node that dies holding the container's progress-board lock, its slot "
              "half-written: the next locker gets EOWNERDEAD, repairs the slot, and "
              "everyone goes on",
    )
    fault = FAULTS["die-holding-robust-mutex"](rig_factory(profile))
    run_trials(fault.trial, fault.settle, quick=3, deep=200)
    resilience.expect_rate("survived", at_least=1.0)
