"""Callbacks that raise or never return."""

import pytest

from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.faults.trials import FAULTS
from cloneguard.harness.rig import Outcome, TrialOutcome


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_uncaught_exception_ends_only_its_node(profile, rig_factory, resilience, run_trials):
    resilience.describe(
        fault="exception",
        profile=profile,
        mitigations={},
        claim="an exception escaping one node's callback ends that node's process "
        "(CRASHED, exit code 1); the rest goes on",
    )
    fault = FAULTS["exception"](rig_factory(profile))
    run_trials(fault.trial, fault.settle, quick=3, deep=200, rig=fault.rig)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)


def test_uncaught_exception_ends_a_thread_mode_container(rig_factory, resilience, record_trial, trial_plan):
    resilience.describe(
        fault="exception",
        profile="threads",
        mitigations={},
        claim="baseline: as with rclcpp, an exception escaping a callback ends the "
        "thread-mode container (exit status 1)",
    )
    [(index, seed)] = trial_plan(1, 1)
    rig = rig_factory("threads")
    rig.client.load_ok(TESTRIG, "faults::RaiseInCallback", parameters={"delay": 0.1})
    code = rig.proc.wait(timeout=10)
    record_trial(
        index, seed, Outcome(TrialOutcome.CRASHED if code == 1 else TrialOutcome.FAILED, details={"exit_code": code})
    )
    resilience.expect_rate(TrialOutcome.CRASHED, at_least=1.0)


@pytest.mark.parametrize("mode", ["sleep", "spin"])
@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_a_hanging_callback_stalls_only_its_node(profile, mode, rig_factory, resilience, record_trial, trial_plan):
    resilience.describe(
        fault=f"hang-{mode}",
        profile=profile,
        mitigations={},
        claim="a callback that never returns stalls only its own node: the others "
        "keep running and the container keeps answering; unloading it works",
    )
    [(index, seed)] = trial_plan(1, 1)
    rig = rig_factory(profile)
    resp = rig.client.load_ok(TESTRIG, "faults::HangInCallback", parameters={"delay": 0.1, "mode": mode})
    pid = rig.loaded_pid(resp.unique_id)
    rig.wait_firing(pid)
    stopped = rig.goes_on()
    out = Outcome(
        TrialOutcome.SURVIVED if stopped is None else TrialOutcome.HUNG, details={"pid": pid, "why": stopped or ""}
    )
    if stopped is None:
        # The hung node cannot stop by itself: unload ends it with SIGKILL.
        unloaded = rig.client.unload(resp.unique_id, timeout=10)
        if not unloaded.success:
            out.outcome, out.details["why"] = TrialOutcome.FAILED, unloaded.error_message
    record_trial(index, seed, out)
    rig.settle(out)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)
