"""pytest plugin: real containers as fixtures, and a leftovers check after each test that starts one.

It changes nothing for a test that uses none of its fixtures: no ROS import
at start-up (rclpy's rcl exits the process with 102 at import when
RMW_IMPLEMENTATION names an rmw that is not installed), no environment
variable set, no check after the test.

Fixtures
    container_args     arguments for the container (override by parametrizing)
    container_env      extra environment for it (override in a test module)
    container_factory  start(args, ...) -> ContainerProcess; stops them after the test
    container          one started container (``container_args``), services up
    client             a ContainerClient connected to ``container``
    system_factory     system_factory(nodes, container_args=None, memory_limit=None) -> System:
                       your own composition (NodeSpecs, or a Composition read from a launch
                       file: composition.py) loaded into a container (default: --isolated),
                       with memory_limit (bytes) in a memory cgroup of that limit
    system_trials      system_trials(system, trial, fault=, claim=, ...): seeded trials
                       of a System, recorded in the report (harness/system_trials.py)
    domain_id          this test's own ROS_DOMAIN_ID
    ros_environment    for the test's duration, this process's participants (the
                       harness's clients) follow the containers' rules: Fast DDS,
                       UDP on loopback only (container_factory uses it)

Options
    --container-exe PATH   the container executable under test (default: ours)
    --container-arg ARG    one more argument for every System's container (repeatable)
    --hold-failed SECONDS  a System's trials stop at the first that does not survive; its
                           container is kept running that long (inf: until Ctrl-C)
    --deep, --trials N, --seed S, --trial-seed S   how many trials scenarios make, from
                           which seeds (plan.py)
    --fault KIND, --node NAME   only the scenarios whose fault/node markers name them
                           (selection.py)

Trial fixtures (plan.py): trial_plan, record_trial, run_trials.

After every test that started a container: its process group is empty, the
harness has no zombie child, and no orphaned /dev/shm/fastrtps_* segment
appeared.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import pytest

from . import domains, plan, procfs, selection, shm
from .plan import record_trial, run_trials, trial_plan  # noqa: F401  (plugin)
from .process import DISCOVERY_RANGE_VARIABLES, loopback_variables
from .system_trials import system_trials  # noqa: F401  (plugin)

if TYPE_CHECKING:
    from .client import ContainerClient
    from .composition import Composition
    from .factory import ContainerFactory
    from .process import ContainerProcess
    from .system import NodeSpec, System

    class SystemFactory(Protocol):
        """What the ``system_factory`` fixture gives a test."""

        def __call__(
            self,
            nodes: Sequence[NodeSpec] | Composition,
            container_args: Sequence[str] | None = None,
            memory_limit: int | None = None,
        ) -> System: ...


def _hold_seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--hold-failed takes seconds (or inf), not {text!r}") from None
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"--hold-failed takes seconds >= 0 (or inf), not {text!r}")
    return value


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("cloneguard")
    group.addoption(
        "--container-exe",
        default=None,
        help="component container executable to test (default: this project's component_container)",
    )
    group.addoption(
        "--container-arg",
        action="append",
        default=[],
        metavar="ARG",
        help="one more argument for every System's container (repeat it; --container-arg=--allocator=glibc)",
    )
    group.addoption(
        "--hold-failed",
        type=_hold_seconds,
        default=None,
        metavar="SECONDS",
        help="stop a System's seeded trials at the first that does not survive and keep its container "
        "running that long for a debugger (inf: until Ctrl-C)",
    )
    group.addoption(
        "--named-fault",
        default=None,
        metavar="NAME",
        help="the fault of yours a package declares as NAME (cloneguard.harness.faults), for the scenario "
        "`reproduce NAME` runs",
    )
    plan.add_options(parser)
    selection.add_options(parser)


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "shm: the test runs Fast DDS with shared memory on")
    selection.register_markers(config)
    # The ROS wheels' rosidl parsers import lark, which imports two modules
    # Python 3.11 deprecates: a warning in every run that is neither the
    # user's nor ours to act on.
    for module in ("sre_parse", "sre_constants"):
        config.addinivalue_line("filterwarnings", f"ignore:module '{module}' is deprecated:DeprecationWarning:lark")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    selection.select(config, items)
    plan.give_long_timeouts(config, items)


@pytest.fixture
def ros_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for key in DISCOVERY_RANGE_VARIABLES:
        monkeypatch.delenv(key, raising=False)
    for key, value in loopback_variables().items():
        monkeypatch.setenv(key, value)


@pytest.fixture
def domain_id() -> Iterator[int]:
    with domains.lease() as lease:
        yield lease.domain_id


@pytest.fixture
def container_args() -> list[str]:
    return []


@pytest.fixture
def container_env() -> dict[str, str]:
    return {}


@pytest.fixture
def container_factory(
    request: pytest.FixtureRequest, ros_environment: None, domain_id: int, tmp_path: Path, _leftovers: _Leftovers
) -> Iterator[ContainerFactory]:
    from .factory import ContainerFactory, log_tail  # imports rclpy: only now, with ros_environment set

    factory = ContainerFactory(domain_id, tmp_path, exe=request.config.getoption("--container-exe"))
    _leftovers.factories.append(factory)
    yield factory
    factory.stop_all()
    for i, proc in enumerate(factory.started):
        request.node.add_report_section("teardown", f"container-{i} log", log_tail(proc.log_text()))


@pytest.fixture
def container(
    container_factory: ContainerFactory, container_args: list[str], container_env: dict[str, str]
) -> ContainerProcess:
    return container_factory.start(container_args, extra_env=container_env)


@pytest.fixture
def client(container_factory: ContainerFactory, container: ContainerProcess) -> ContainerClient:
    return container_factory.connect(container)


@pytest.fixture
def system_factory(request: pytest.FixtureRequest, container_factory: ContainerFactory) -> SystemFactory:
    from .composition import Composition
    from .system import System

    more = list(request.config.getoption("--container-arg"))
    made: list[System] = []

    def make(
        nodes: Sequence[NodeSpec] | Composition,
        container_args: Sequence[str] | None = None,
        memory_limit: int | None = None,
    ) -> System:
        running = [s for s in made if s.alive()]
        if running:
            # Every container of a test shares its ROS domain and is named
            # /ComponentManager: a second one's loads, topics and services
            # would reach the first's.
            raise RuntimeError(
                "one running System at a time in a test: the first is still running "
                f"({' '.join(running[0].container_args) or 'thread mode'}); stop it first with its stop()"
            )
        if isinstance(nodes, Composition):  # read from a file: its arguments unless given
            container_args = container_args if container_args is not None else nodes.container_args
            nodes = nodes.nodes
        args = ("--isolated",) if container_args is None else container_args
        made.append(System(container_factory, nodes, [*args, *more], memory_limit=memory_limit))
        return made[-1]

    return make


JANITOR_GRACE_S = 10.0


class _Leftovers:
    def __init__(self) -> None:
        self.factories: list = []  # the ContainerFactory of each test
        self.shm_before = shm.segments()

    def problems(self) -> list[str]:
        found = []
        for factory in self.factories:
            for proc in factory.started:
                members = proc.group_members()
                if members:
                    found.append(f"processes left in group {proc.pgid}: {members}")
                # Only cgroups it made: a dead container of an earlier run
                # that had the same pid may have left one of that name. A
                # container that ended without its shutdown leaves them to
                # its cgroup janitor, which removes them just after.
                cgroups = [
                    d
                    for d in procfs.cgroup_dirs_named(f"cloneguard-{proc.pid}")
                    if d.stat().st_ctime >= proc.started_at
                ]
                cgroups = procfs.wait_gone(cgroups, JANITOR_GRACE_S)
                if cgroups:
                    found.append(f"cgroups left behind: {[str(d) for d in cgroups]}")
        zombies = procfs.zombies_of(os.getpid())
        if zombies:
            found.append(f"zombie children of the harness: {zombies}")
        # A segment that appeared during the test, that one of our containers
        # was seen to map, and whose owner is gone (its lock file can be
        # locked), or a port with no lock file that no live process maps, was
        # left by a process the test stopped: reported and removed. Every
        # container of the test has been stopped by now (a process left in
        # its group is reported above), so none of ours can still be opening
        # one. Anything else (in use, or never ours) is left alone. A test
        # that kills a container while another lives stops that one before
        # cleaning up after the death itself.
        new_segments = shm.segments() - self.shm_before
        ours = set().union(*(p.shm_seen for f in self.factories for p in f.started))
        if new_segments and ours:
            orphans = shm.remove_orphans_of(new_segments, ours)
            if orphans:
                names = [seg.name + (" (lock-less port)" if seg.lockless else "") for seg in orphans]
                found.append(f"orphaned /dev/shm segments (now removed): {names}")
        return found


@pytest.fixture
def _leftovers() -> Iterator[_Leftovers]:
    tracker = _Leftovers()
    yield tracker
    problems = tracker.problems()
    if problems:
        pytest.fail("test left things behind:\n  " + "\n  ".join(problems), pytrace=False)
