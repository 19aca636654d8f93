"""Faults of yours, by name: seeded trials of a composition of yours that
your package declares in the entry point group ``cloneguard.harness.faults``,
so that your scenarios run them and ``python -m cloneguard.harness
reproduce NAME`` replays them, as it does the project's own faults.

    # your_package/faults.py
    PLANNER_HOLDING_A_LOCK = NamedFault(
        fault="planner SIGKILL holding a Python lock",
        claim="odometry keeps >= 9 Hz",
        nodes=ROBOT,
        trials=planner_lock_trials,     # (system) -> trial(t), as system_trials takes
        at_least=0.99,
    )

    # pyproject.toml
    [project.entry-points."cloneguard.harness.faults"]
    planner-holding-a-lock = "your_package.faults:PLANNER_HOLDING_A_LOCK"

    # scenarios/test_robot.py
    def test_planner_holding_a_lock(system_factory, system_trials):
        PLANNER_HOLDING_A_LOCK.run(system_factory, system_trials)

Public and kept stable, like system.py.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .composition import Composition
    from .pytest_plugin import SystemFactory
    from .report.stats import Proportion
    from .system import NodeSpec
    from .system_trials import SystemTrials

GROUP = "cloneguard.harness.faults"


@dataclass(frozen=True)
class NamedFault:
    """Seeded trials of a composition: ``trials(system)`` is called once
    the System is up (start watching topics there) and returns the trial
    function ``system_trials`` runs (``trial(t)`` with a SystemTrial).
    ``fault``, ``claim``, ``quick``, ``deep`` and ``at_least`` are what
    ``system_trials`` takes; ``nodes`` and ``container_args`` what
    ``system_factory`` takes (a list of NodeSpec or a read Composition)."""

    fault: str
    claim: str
    nodes: Sequence[NodeSpec] | Composition
    trials: Callable[..., Callable[..., Mapping | None]]
    container_args: Sequence[str] | None = None
    quick: int = 3
    deep: int = 200
    at_least: float | None = None

    def run(self, system_factory: SystemFactory, system_trials: SystemTrials) -> Proportion:
        """Start the composition and run its trials (in a test, with its
        fixtures); the survival rate, as ``system_trials`` returns it."""
        system = system_factory(self.nodes, self.container_args)
        return system_trials(
            system,
            self.trials(system),
            fault=self.fault,
            claim=self.claim,
            quick=self.quick,
            deep=self.deep,
            at_least=self.at_least,
        )


def names() -> list[str]:
    """The names every installed package declares."""
    return sorted(ep.name for ep in entry_points(group=GROUP))


def load(name: str) -> NamedFault:
    """The NamedFault declared as ``name``; LookupError saying what there is
    when there is no such name, TypeError when it is not a NamedFault."""
    found = [ep for ep in entry_points(group=GROUP) if ep.name == name]
    if not found:
        known = ", ".join(names()) or "none is installed"
        raise LookupError(f"no fault {name!r} in the entry point group {GROUP} ({known})")
    if len(found) > 1:
        raise LookupError(f"{len(found)} packages declare the fault {name!r}: {', '.join(ep.value for ep in found)}")
    fault = found[0].load()
    if not isinstance(fault, NamedFault):
        raise TypeError(f"{GROUP} {name!r} = {found[0].value} is a {type(fault).__name__}, not a NamedFault")
    return fault


#: The test ``reproduce NAME`` runs with pytest (``--named-fault NAME``).
SCENARIO = Path(__file__).resolve().parent / "scenarios" / "test_named_fault.py"
