"""SIGKILL of one node's process from outside, at a random instant."""

import pytest

from cloneguard.faults.trials import FAULTS
from cloneguard.harness.plan import DEEP_FLOOR_TRIALS
from cloneguard.harness.rig import TrialOutcome


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_random_sigkill_of_a_busy_node(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault="sigkill-outside",
        profile=profile,
        mitigations={},
        claim="a node's process SIGKILLed at a random instant while it publishes at "
        "500 Hz is reported CRASHED (SIGKILL) and the rest goes on",
    )
    fault = FAULTS["sigkill-outside"](rig_factory(profile))
    planned = run_trials(fault.trial, fault.settle, quick=5, deep=300, rig=fault.rig)
    floor = FLOOR[profile] if planned >= DEEP_FLOOR_TRIALS else QUICK_FLOOR[profile]
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=floor)


# Per-node: 1,199 of 1,200 over deep-5..8 (docs/evidence.md); the one hang
# (deep-8) was the next node being built, inside rclpy with the GIL, waiting
# on a Fast DDS payload-pool lock (rt/rosout's, shared by every participant
# of the process) that the killed node's process held. Shared: 298/300; both
# hangs were the container waiting on a mutex of its own DDS participant
# that the killed node's process held (shared-profile nodes publish through
# the container's participant: a kill there is outside what any mitigation
# here covers). On a quick run's 5 trials the floor is 4 of 5 (a 99.3% rate
# misses it once in ~4,000 runs; 5 of 5 would fail one run in 30).
FLOOR = {"per-node": 0.99, "shared": 0.98}
QUICK_FLOOR = {"per-node": 0.8, "shared": 0.8}
