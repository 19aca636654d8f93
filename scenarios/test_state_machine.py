"""Random sequences of load / unload / crash against a model of the container.

A hypothesis rule-based state machine drives a real isolated container.
Invariants after every step: ListNodes equals the model; every node that
died was reported CRASHED exactly once; the container is alive. Each example
(one container, a sequence of steps) is one trial: failed if any step or
invariant raised (hypothesis then shrinks: each replay is a trial too).
"""

import collections
import functools
import os
import signal

import pytest
from cloneguard_interfaces.msg import ComponentEvent
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.stateful import Bundle, RuleBasedStateMachine, consumes, invariant, rule, run_state_machine_as_test

from cloneguard.harness.plan import trial_count
from cloneguard.harness.rig import Outcome, TrialOutcome

PLUGINS = ["cloneguard::Talker", "cloneguard::Listener", "cloneguard::Heartbeat", "cloneguard::EchoService"]


def checked(step):
    """A rule or invariant that marks the example failed when it raises
    (teardown runs for failing examples too)."""

    @functools.wraps(step)
    def run(self, *args, **kwargs):
        try:
            return step(self, *args, **kwargs)
        except BaseException as exc:
            self.failure = self.failure or f"{step.__name__}: {type(exc).__name__}: {exc}"
            raise

    return run


def make_machine(start_rig, on_example_end):
    class ContainerMachine(RuleBasedStateMachine):
        nodes = Bundle("nodes")

        def __init__(self):
            super().__init__()
            self.rig = start_rig()
            self.cli = self.rig.client
            self.model = {self.rig.survivor_id: "/survivor"}
            self.crashed = set()
            self.counter = 0
            self.failure = None

        @rule(target=nodes, plugin=st.sampled_from(PLUGINS))
        @checked
        def load(self, plugin):
            self.counter += 1
            name = f"n{self.counter}"
            resp = self.cli.load_ok("cloneguard", plugin, node_name=name)
            self.model[resp.unique_id] = f"/{name}"
            return resp.unique_id

        @rule(uid=consumes(nodes))
        @checked
        def unload(self, uid):
            resp = self.cli.unload(uid)
            assert resp.success, resp.error_message
            del self.model[uid]

        @rule(uid=consumes(nodes), sig=st.sampled_from([signal.SIGKILL, signal.SIGSEGV, signal.SIGABRT]))
        @checked
        def crash(self, uid, sig):
            pid = self.rig.loaded_pid(uid)
            os.kill(pid, sig)
            ev = self.cli.wait_for_event(ComponentEvent.CRASHED, unique_id=uid, timeout=10)
            assert ev.exit_signal == sig
            del self.model[uid]
            self.crashed.add(uid)

        @rule(missing=st.integers(min_value=10_000, max_value=20_000))
        @checked
        def unload_missing(self, missing):
            resp = self.cli.unload(missing)
            assert not resp.success and resp.error_message == f"No node found with unique_id: {missing}"

        @invariant()
        @checked
        def listnodes_equals_model(self):
            assert self.rig.proc.alive(), "the container died"
            assert dict(self.cli.list()) == self.model

        @invariant()
        @checked
        def every_death_reported_once(self):
            counts = collections.Counter(
                e.unique_id for e in self.cli.events.messages() if e.event_type == ComponentEvent.CRASHED
            )
            assert set(counts) == self.crashed and all(n == 1 for n in counts.values()), counts

        def teardown(self):
            on_example_end(self)

    return ContainerMachine


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_random_operation_sequences_keep_the_invariants(
    profile, rig_factory, resilience, record_trial, trial_plan, request
):
    resilience.describe(
        fault="random load/unload/crash sequences",
        profile=profile,
        mitigations={},
        claim="any sequence of load, unload, unload of a missing id and crash (SIGKILL, "
        "SIGSEGV, SIGABRT from outside) keeps ListNodes equal to the model and "
        "reports every death exactly once",
    )
    rigs = []

    def start():
        rig = rig_factory(profile)
        rigs.append(rig)
        return rig

    def end(machine):
        details = {"model_size": len(machine.model)}
        if machine.failure:
            details["why"] = machine.failure
        record_trial(
            len(rigs) - 1,
            0,
            Outcome(TrialOutcome.FAILED if machine.failure else TrialOutcome.SURVIVED, details=details),
        )
        machine.rig.client.close()
        machine.rig.proc.stop()

    trial_plan(1, 1)  # hypothesis draws the examples; one shard runs them
    examples = trial_count(request.config, 3, 200)
    run_state_machine_as_test(
        make_machine(start, end),
        settings=settings(
            max_examples=examples,
            stateful_step_count=8,
            deadline=None,
            suppress_health_check=list(HealthCheck),
            database=None,
        ),
    )
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=1.0)
