"""A node dies holding a lock of the container's (a robust mutex)."""
import pytest

from faults.trials import die_holding_lock


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_death_holding_a_container_lock_is_repaired(profile, rig_factory, resilience, record_trial, trials, rng):
    resilience.describe(
        fault="die-holding-robust-mutex", profile=profile, mitigations={"robust_mutex": True},
        claim="a node that dies holding the container's progress-board lock, its slot "
              "half-written: the next locker gets EOWNERDEAD, repairs the slot, and "
              "everyone goes on",
    )
    rig = rig_factory(profile)
    for i in range(trials(3, 200)):
        seed = rng.getrandbits(31)
        out = die_holding_lock(rig, seed, i)
        record_trial(i, seed, out)
        rig.settle(out)
    resilience.expect_rate("survived", at_least=1.0)
