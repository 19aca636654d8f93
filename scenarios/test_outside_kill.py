"""SIGKILL of one node's process from outside, at a random instant."""
import pytest

from faults.trials import outside_sigkill


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_random_sigkill_of_a_busy_node(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault="sigkill-outside", profile=profile, mitigations={},
        claim="a node's process SIGKILLed at a random instant while it publishes at "
              "500 Hz is reported CRASHED (SIGKILL) and the rest goes on",
    )
    rig = rig_factory(profile)
    run_trials(lambda seed, i: outside_sigkill(rig, seed, i), rig.settle, quick=5, deep=300)
    resilience.expect_rate("survived", at_least=1.0)
