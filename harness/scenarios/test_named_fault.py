"""The scenario ``python -m cloneguard.harness reproduce NAME`` runs: the
trials of the fault a package of yours declares as NAME (named_faults.py),
given to pytest as ``--named-fault NAME``. Not a package: pytest imports it
by path (``--import-mode=importlib``), and it imports only the harness."""

from __future__ import annotations

from typing import TYPE_CHECKING

from cloneguard.harness import named_faults

if TYPE_CHECKING:
    import pytest

    from cloneguard.harness.pytest_plugin import SystemFactory
    from cloneguard.harness.system_trials import SystemTrials


def test_named_fault(
    request: pytest.FixtureRequest, system_factory: SystemFactory, system_trials: SystemTrials
) -> None:
    name = request.config.getoption("--named-fault")
    if name is None:
        raise AssertionError("run this with --named-fault NAME (python -m cloneguard.harness reproduce NAME)")
    named_faults.load(name).run(system_factory, system_trials)
