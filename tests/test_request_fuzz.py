"""A hostile client, property-based: random sequences of LoadNode, UnloadNode
and ListNodes requests (harness/fuzz.py), alone and in concurrent bursts,
against one real container per set-up.

After every step: the container answers and ListNodes equals the model;
every answer is consistent with it (an id is never given twice and only
grows, valid loads succeed, failures say why, an unload succeeds exactly
when its id is live). After every example (a sequence of steps, then
everything unloaded): no node process is left, nothing the example loaded
is still in the ROS graph, no failed load left its node's process in
memory, and the container's fds and threads are within what it had after a
warm-up burst.

The quick budget runs with the tests; ``--deep`` (or ``--trials N``: N
requests) makes at least DEEP_REQUESTS requests per set-up. Examples are
not shrunk: the container's history is part of each example's starting
state, so a replay would not be the same example; a failure prints the
steps as they ran.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import pytest
import rclpy
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, precondition, rule, run_state_machine_as_test
from rclpy.context import Context

from cloneguard.container.isolated.cgroups import cgroup2_mount
from cloneguard.harness import fuzz, procfs, rest
from cloneguard.harness.plan import long_run

MODES = {
    "threads": [],
    "per-node": ["--isolated", "--profile", "per-node"],
    "shared": ["--isolated", "--profile", "shared"],
    "cgroups": ["--isolated", "--cgroups"],
}
# The per-node profile keeps one process made ahead for the next load (its
# warm spare), with a hidden placeholder node named for its pid.
KEEPS_A_SPARE = {"per-node"}
QUICK = dict(examples=3, steps=12)
DEEP_REQUESTS = 1000
DEEP = dict(examples=20, steps=40)
MAX_LIVE = 12  # more would only slow the run (per-node: a process each)
GRAPH_SETTLE_S = 10.0  # discovery of a node's departure
OBSERVE_S = 3.0  # a new observer's look at the graph, once it sees the container


class World:
    """What outlives one example: the container, its client, the ids it gave."""

    def __init__(self, container, client, cgroups: bool, spare: bool):
        self.container, self.client, self.cgroups, self.spare = container, client, cgroups, spare
        self.model = fuzz.Model()
        # The container answered ListNodes, but node names travel on their
        # own topic (ros_discovery_info): a baseline taken before the
        # container's name arrived made the container itself a "ghost".
        deadline = time.monotonic() + 10.0
        while container.fqn not in self.graph():
            assert time.monotonic() < deadline, f"{container.fqn} not in the client's graph within 10 s"
            time.sleep(0.05)
        self.baseline_graph = self.graph()
        self.fds = self.threads = 0
        self.rss_kib: list[int] = []
        self.examples = 0
        self.stale_ghosts = 0  # left only in the long-lived client's graph cache

    def graph(self) -> set[str]:
        """The nodes the client's graph holds, but the placeholder of a live
        spare (one whose process is gone is a ghost like any other)."""
        spares = {f"/{rest.SPARE_PLACEHOLDER}{pid}" for pid in procfs.children_of(self.container.pid)}
        return {(ns.rstrip("/") + "/" + name) for name, ns in self.client.node.get_node_names_and_namespaces()} - spares

    def at_rest(self) -> list[int]:
        """The container's child processes once nothing is loaded: none, or
        its spare, made (again, off the request path, after each load)."""
        return rest.wait_at_rest(self.client.node, self.container.pid, spare=self.spare)

    def ghosts(self, within: float) -> set[str]:
        """Nodes in the graph that are not the container's, the harness's or
        loaded, once they have had ``within`` seconds to go."""
        deadline = time.monotonic() + within
        while (ghosts := self.graph() - self.baseline_graph - self.model.node_names()) and time.monotonic() < deadline:
            time.sleep(0.1)
        return ghosts

    def resources(self) -> tuple[int, int, int]:
        pid = self.container.pid
        return (
            len(procfs.lasting_fds(pid)),
            len(os.listdir(f"/proc/{pid}/task")),
            procfs.rss_kib(pid),
        )

    def warm_up(self) -> None:
        """A burst as wide as the container's thread pools, so that they
        are at their bound before anything is counted."""
        client = self.client
        uids, lock = [], threading.Lock()

        def one():
            resp = client.load_ok(fuzz.PKG, "cloneguard::Heartbeat")
            with lock:
                uids.append(resp.unique_id)

        threads = [threading.Thread(target=one) for _ in range(16)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for uid in uids:
            assert client.unload(uid).success
        self.model.given.update(uids)
        self.model.highest = max(uids)
        self.at_rest()
        self.fds, self.threads, _ = self.resources()


def fresh_observer_graph(domain_id: int, container_fqn: str) -> set[str]:
    """Every node a new participant discovers within OBSERVE_S of first
    seeing the container's."""
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    node = rclpy.create_node("fuzz_observer", context=context)
    seen: set[str] = set()
    try:
        deadline = time.monotonic() + 10.0
        until = None
        while time.monotonic() < (until or deadline):
            names = {(ns.rstrip("/") + "/" + n) for n, ns in node.get_node_names_and_namespaces()}
            seen |= names
            if until is None and container_fqn in names:
                until = time.monotonic() + OBSERVE_S
            time.sleep(0.1)
        assert until is not None, "a new observer did not discover the container within 10 s"
    finally:
        node.destroy_node()
        rclpy.shutdown(context=context)
    return seen


def make_machine(world: World):
    client, model = world.client, world.model

    class HostileClient(RuleBasedStateMachine):
        def __init__(self):
            super().__init__()
            assert client.list() == [], "an example must start with nothing loaded"

        # -- one request at a time ----------------------------------------------

        @precondition(lambda self: len(model.live) < MAX_LIVE)
        @rule(load=fuzz.valid_loads(cgroups=world.cgroups))
        def load_valid(self, load):
            model.apply_load(load, client.send_load(load.request, 70.0))

        @rule(load=fuzz.hostile_loads())
        def load_hostile(self, load):
            model.apply_load(load, client.send_load(load.request, 70.0))

        @precondition(lambda self: len(model.live) < MAX_LIVE)
        @rule(load=fuzz.hostile_parameter_loads())
        def load_hostile_parameters(self, load):
            model.apply_load(load, client.send_load(load.request, 70.0))

        @rule(data=st.data())
        def unload(self, data):
            uid = data.draw(fuzz.unload_ids(sorted(model.live), model.gone[-20:]), label="unique_id")
            model.apply_unload(uid, client.unload(uid))

        @rule()
        def list_nodes(self):
            model.requests += 1
            assert client.list() == model.listed()

        # -- several clients at once ----------------------------------------------

        @rule(data=st.data())
        def burst(self, data):
            live = sorted(model.live)
            kinds = ["valid", "hostile", "list"] + (["unload", "unload-same"] if live else [])
            plan = data.draw(st.lists(st.sampled_from(kinds), min_size=2, max_size=6), label="burst")
            if len(model.live) + plan.count("valid") > MAX_LIVE:
                plan = [k for k in plan if k != "valid"] or ["list", "list"]
            loads = [
                data.draw(fuzz.valid_loads(cgroups=world.cgroups) if k == "valid" else fuzz.hostile_loads(), label=k)
                for k in plan
                if k in ("valid", "hostile")
            ]
            unloads = [data.draw(st.sampled_from(live), label="unload") for k in plan if k == "unload"]
            same = data.draw(st.sampled_from(live), label="unload-same") if "unload-same" in plan else None
            unloads += [same] * (2 * plan.count("unload-same"))
            results: dict[int, Any] = {}

            def run(i, call):
                results[i] = call()

            calls: list[Callable[[], object]] = [partial(client.send_load, ld.request, 70.0) for ld in loads]
            calls += [partial(client.unload, uid, timeout=70.0) for uid in unloads]
            calls += [lambda: client.list(timeout=70.0)] * plan.count("list")
            threads = [threading.Thread(target=run, args=(i, c)) for i, c in enumerate(calls)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            missing = [i for i in range(len(calls)) if i not in results]
            assert not missing, f"{len(missing)} of {len(calls)} concurrent requests got no answer"
            # Loads in the order of the ids they got (ids only grow).
            answered = sorted(
                zip(loads, (results[i] for i in range(len(loads))), strict=True),
                key=lambda lr: lr[1].unique_id if lr[1].success else 0,
            )
            for load, resp in answered:
                model.apply_load(load, resp)
            by_id: dict[int, list] = {}
            for j, uid in enumerate(unloads):
                by_id.setdefault(uid, []).append(results[len(loads) + j])
            for uid, responses in by_id.items():
                model.apply_unloads_at_once(uid, responses)
            model.requests += plan.count("list")

        # -- after every step -----------------------------------------------------

        @invariant()
        def lists_what_the_model_holds(self):
            assert world.container.alive(), "the container exited"
            assert client.list() == model.listed()

        def teardown(self):
            world.examples += 1
            if not world.container.alive():
                return
            for uid in sorted(model.live):
                model.apply_unload(uid, client.unload(uid, timeout=70.0))
            assert client.list() == []
            assert len(world.at_rest()) == (1 if world.spare else 0), "node processes left at rest"
            # No request crashes a node's process, so none may leave one's
            # objects behind (a failed construction whose process did not end).
            assert "left in memory" not in world.container.log_text(), "a failed load leaked its node's process"
            ghosts = world.ghosts(GRAPH_SETTLE_S)
            if ghosts:
                # A graph cache that outlived many participants can keep
                # one that left (an observer-side race in rmw): what counts
                # is what a new observer discovers.
                seen = fresh_observer_graph(world.container.domain_id, world.container.fqn) & ghosts
                world.stale_ghosts += len(ghosts - seen)
                assert not seen, (
                    f"nodes still in the ROS graph {GRAPH_SETTLE_S:g} s after their unload, "
                    f"also for a new observer: {sorted(seen)}"
                )
            fds, threads, rss = world.resources()
            world.rss_kib.append(rss)
            assert fds <= world.fds, f"open fds {world.fds} -> {fds}"
            assert threads <= world.threads, f"threads {world.threads} -> {threads}"

    return HostileClient


@pytest.mark.timeout(900)
@pytest.mark.parametrize("mode", list(MODES))
def test_hostile_requests_never_end_wedge_or_drain_the_container(mode, request, container_factory):
    if mode == "cgroups" and cgroup2_mount() is None:
        pytest.skip("no cgroup2 here")
    container = container_factory.start(MODES[mode])
    world = World(
        container, container_factory.connect(container), cgroups=mode == "cgroups", spare=mode in KEEPS_A_SPARE
    )
    world.warm_up()
    config = request.config
    deep = long_run(config)
    target = config.getoption("--trials") or DEEP_REQUESTS if deep else 0
    budget = DEEP if deep else QUICK
    rounds = 0
    while True:
        rounds += 1
        run_state_machine_as_test(
            make_machine(world),
            settings=settings(
                max_examples=budget["examples"],
                stateful_step_count=budget["steps"],
                deadline=None,
                derandomize=not deep,
                database=None,
                phases=[Phase.generate],
                report_multiple_bugs=False,
                suppress_health_check=list(HealthCheck),
            ),
        )
        if world.model.requests >= target:
            break
    rss = world.rss_kib
    print(
        f"{mode}: {world.model.requests} requests in {world.examples} examples ({rounds} round(s)); "
        f"ids given {len(world.model.given)}; {world.stale_ghosts} stale in the client's graph only; "
        f"fds {world.fds}, threads {world.threads} at most; "
        f"RSS {rss[0] / 1024:.1f} -> {rss[-1] / 1024:.1f} MiB at rest"
    )
    container.stop()
    assert container.exit_status.returncode == 0 and not container.exit_status.forced
