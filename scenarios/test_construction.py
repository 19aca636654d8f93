"""Nodes that are slow to build, die while being built, or whose LOADED
event is lost: what the launcher-side tracker reports."""

import os
import random
import signal

import pytest
from cloneguard_interfaces.msg import ComponentEvent

from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness import procfs
from cloneguard.harness.rig import Outcome, TrialOutcome
from cloneguard.harness.tracker import NodeTracker, State

DROP = {"cloneguard.fault.drop_loaded_event": True}


@pytest.fixture
def tracked(rig_factory):
    made = []

    def make(profile, **rig_options):
        rig = rig_factory(profile, **rig_options)
        tracker = NodeTracker(rig.client)
        made.append(tracker)
        return rig, tracker

    yield make
    for t in made:
        t.close()


@pytest.mark.parametrize("profile", ["threads", "per-node"])
def test_slow_constructor_is_loaded_not_failed(profile, tracked, resilience, record_trial, trial_plan):
    [(index, seed)] = trial_plan(1, 1)
    resilience.describe(
        fault="slow-constructor-12s",
        profile=profile,
        mitigations={},
        claim="a node that takes 12 s to construct (longer than the 10 s loading "
        "fallback) ends Loaded through its LOADED event, not through the fallback",
    )
    rig, tracker = tracked(profile)
    node = tracker.load(TESTRIG, "faults::SlowConstructor", parameters={"seconds": 12.0}, timeout=40)
    state = tracker.wait_state(node, [State.LOADED, State.FAILED], timeout=10)
    ok = state == State.LOADED and not node.warnings
    record_trial(
        index,
        seed,
        Outcome(
            TrialOutcome.SURVIVED if ok else TrialOutcome.FAILED,
            details={"state": state.value, "warnings": node.warnings},
        ),
    )
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_node_killed_mid_construction_is_never_loaded(profile, tracked, resilience, record_trial, trial_plan):
    resilience.describe(
        fault="die-in-constructor (SIGKILL, SIGSEGV or SIGABRT, drawn)",
        profile=profile,
        mitigations={},
        claim="a node whose process dies while it is being built is reported "
        "Failed (LoadNode fails), never Loaded; the container goes on",
    )
    rig, tracker = tracked(profile)
    for index, seed in trial_plan(3, 200):
        sig = random.Random(seed).choice(["SIGKILL", "SIGSEGV", "SIGABRT"])
        node = tracker.load(TESTRIG, "faults::DieInConstructor", parameters={"signal": sig})
        ok = node.state == State.FAILED and "died during construction" in node.error
        out = Outcome(
            TrialOutcome.SURVIVED if ok else TrialOutcome.FAILED,
            details={"signal": sig, "state": node.state.value, "error": node.error},
        )
        stopped = rig.goes_on()
        if stopped is not None:
            record_trial(index, seed, rig.not_survived(stopped, out))  # hung (diagnosed) or crashed
            break  # no container left to try the next trials in: they are not recorded
        if not ok:
            out.details["why"] = "not reported Failed with 'died during construction'"
        record_trial(index, seed, out)
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)


def test_lost_loaded_event_falls_back_after_listnodes_confirms(tracked, resilience, record_trial, trial_plan):
    [(index, seed)] = trial_plan(1, 1)
    resilience.describe(
        fault="lost-loaded-event",
        profile="per-node",
        mitigations={"listnodes_confirmation": True},
        claim="a node whose LOADED event is lost is promoted to Loaded 10 s after its "
        "LoadNode succeeded, only once ListNodes shows it, with a warning",
    )
    rig, tracker = tracked("per-node")
    node = tracker.load("cloneguard", "cloneguard::Talker", extra_arguments=DROP)
    assert node.state == State.LOADING
    state = tracker.wait_state(node, [State.LOADED, State.FAILED], timeout=20)
    promoted_after = node.history[-1][0] - node.answered_at
    ok = state == State.LOADED and any("ListNodes confirms" in w for w in node.warnings)
    record_trial(
        index,
        seed,
        Outcome(
            TrialOutcome.SURVIVED if ok else TrialOutcome.FAILED,
            latency_ms={"answer_to_promotion": promoted_after * 1000},
            details={"state": state.value, "warnings": node.warnings},
        ),
    )
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)


def test_lost_events_and_a_dead_node_are_never_loaded(tracked, resilience, record_trial, trial_plan):
    [(index, seed)] = trial_plan(1, 1)
    resilience.describe(
        fault="lost-loaded-event+sigkill",
        profile="per-node",
        mitigations={"listnodes_confirmation": True},
        claim="a node whose LOADED and CRASHED events are both lost and that is gone "
        "when the 10 s fallback looks is marked Failed, never Loaded",
    )
    # No warm spare: it would be a second child that no event named.
    rig, tracker = tracked("per-node", extra_args=["--no-warm-spare"])
    node = tracker.load("cloneguard", "cloneguard::Talker", extra_arguments=DROP)
    # Without its LOADED event the harness finds the node's process the
    # black-box way: the container's one child that no event named.
    known = set(rig.client.nodes_by_pid())
    (pid,) = [p for p in procfs.children_of(rig.proc.pid) if p not in known]
    rig.client.events.remove_listener(tracker._on_event)  # the CRASHED event is "lost"
    os.kill(pid, signal.SIGKILL)
    rig.client.wait_for_event(ComponentEvent.CRASHED, unique_id=node.unique_id)
    rig.client.events.add_listener(tracker._on_event)
    state = tracker.wait_state(node, [State.LOADED, State.FAILED], timeout=20)
    record_trial(
        index,
        seed,
        Outcome(
            TrialOutcome.SURVIVED if state == State.FAILED else TrialOutcome.FAILED,
            details={"state": state.value, "warnings": node.warnings},
        ),
    )
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)
