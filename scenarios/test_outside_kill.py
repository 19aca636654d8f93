"""SIGKILL of one node's process from outside, at a random instant."""
import pytest

from faults.trials import outside_sigkill


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_random_sigkill_of_a_busy_node(profile, rig_factory, resilience, record_trial, trials, rng):
    resilience.describe(
        fault="sigkill-outside", profile=profile, mitigations={},
        claim="a node's process SIGKILLed at a random instant while it publishes at "
              "500 Hz is reported CRASHED (SIGKILL) and the rest goes on",
    )
    rig = rig_factory(profile)
    for i in range(trials(5, 300)):
        seed = rng.getrandbits(31)
        out = outside_sigkill(rig, seed, i)
        record_trial(i, seed, out)
        rig.settle(out)
    resilience.expect_rate("survived", at_least=1.0)
