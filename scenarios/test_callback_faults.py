"""A node's callback faults: does the rest of the container go on?

In thread mode there is one process: a fatal signal in any callback ends
the container (the baseline the isolated profiles are measured against).
In isolated mode the node's own process dies, the death is reported with
its signal, and everything else goes on.
"""

import pytest

from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.faults.trials import CALLBACK_FAULTS, FAULTS, callback_fault
from cloneguard.harness.rig import Outcome, TrialOutcome


@pytest.mark.parametrize("profile", ["per-node", "shared"])
@pytest.mark.parametrize("fault", list(CALLBACK_FAULTS))
def test_isolated_node_dies_alone(fault, profile, rig_factory, resilience, run_trials):
    sig = CALLBACK_FAULTS[fault][2]
    resilience.describe(
        fault=fault,
        profile=profile,
        mitigations={},
        claim=f"{fault} in one node's callback kills only that node: CRASHED with "
        f"{sig.name}, the other nodes and the container go on",
    )
    trials = FAULTS[fault](rig_factory(profile))
    run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)


@pytest.mark.parametrize("fault", list(CALLBACK_FAULTS))
def test_thread_mode_loses_the_whole_container(fault, rig_factory, resilience, record_trial, trial_plan):
    """The baseline: the same fault in thread mode takes the container down."""
    plugin, params, sig = CALLBACK_FAULTS[fault]
    resilience.describe(
        fault=fault,
        profile="threads",
        mitigations={},
        claim=f"baseline: {fault} in one node's callback ends the whole thread-mode container",
    )
    rig = rig_factory("threads")
    for n, (i, seed) in enumerate(trial_plan(2, 20)):
        if n:
            rig.restart()  # the previous trial's container is gone
        rig.client.load_ok(TESTRIG, plugin, parameters={**params, "delay": 0.1, "seed": seed})
        code = rig.proc.wait(timeout=10)
        out = Outcome(TrialOutcome.CRASHED if code == -sig else TrialOutcome.FAILED, details={"exit_code": code})
        record_trial(i, seed, out)
    resilience.expect_rate(TrialOutcome.CRASHED, at_least=1.0)


def test_without_gil_repair_a_death_holding_the_gil_freezes_the_container(
    rig_factory, resilience, record_trial, trial_plan
):
    """What the GIL repair buys: the same fault with it switched off."""
    resilience.describe(
        fault="segfault-gil-held",
        profile="per-node",
        mitigations={"gil_repair": False},
        claim="with --no-gil-repair, a node that dies holding the GIL freezes the whole "
        "container (the hang is diagnosed: every thread waits on a GIL owned by the dead node)",
    )
    [(index, seed)] = trial_plan(1, 1)
    rig = rig_factory("per-node", extra_args=["--no-gil-repair"])
    out = callback_fault(rig, "segfault-gil-held", seed, index)
    record_trial(index, seed, out)
    resilience.expect_rate(TrialOutcome.SURVIVED, at_most=0.0)
    assert out.outcome == TrialOutcome.HUNG, out.details
    if out.diagnosis is not None:  # gdb is installed by setup; name the GIL owner
        assert any(b.kind == "GIL" and b.owner_dead for b in out.diagnosis.blocked), out.diagnosis.summary()
