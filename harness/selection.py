"""Which scenarios a run takes, by what they hurt: the ``fault`` and
``node`` markers a scenario carries, and ``--fault`` / ``--node`` to pick
by them (public: docs/testing-your-nodes.md).

    @pytest.mark.fault("SIGKILL", "freeze")
    @pytest.mark.node("/planner")
    def test_the_rest_outlives_the_planner(system_factory, system_trials): ...

    pytest scenarios --fault SIGKILL --node /planner

With ``--fault`` given, a test runs only if a ``fault`` marker of its names
one of those faults; with ``--node``, only if a ``node`` marker names one of
those nodes; with both, both must hold. The others are deselected (pytest
counts them so). Names compare exactly: the markers are the test author's
words, as the report's fault column is.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import pytest

MARKERS = {
    "fault": "fault(*kinds): the faults this scenario injects (SIGKILL, freeze, python-lock, ...), for --fault",
    "node": "node(*full_names): the nodes this scenario hurts (/planner), for --node",
}


def add_options(parser: pytest.Parser) -> None:
    group = parser.getgroup("cloneguard")
    group.addoption(
        "--fault",
        action="append",
        default=[],
        metavar="KIND",
        help="run only scenarios marked @pytest.mark.fault(KIND, ...) (repeat for any of several)",
    )
    group.addoption(
        "--node",
        action="append",
        default=[],
        metavar="NAME",
        help="run only scenarios marked @pytest.mark.node(NAME, ...) (repeat for any of several)",
    )


def register_markers(config: pytest.Config) -> None:
    for text in MARKERS.values():
        config.addinivalue_line("markers", text)


def _named(item: pytest.Item, marker: str) -> set[str]:
    return {str(arg) for mark in item.iter_markers(marker) for arg in mark.args}


def select(config: pytest.Config, items: list) -> None:
    """Deselect the tests whose markers name none of the --fault kinds or
    none of the --node names asked for."""
    wanted = {marker: set(config.getoption(f"--{marker}")) for marker in MARKERS}
    if not any(wanted.values()):
        return
    keep: list = []
    drop: list = []
    for item in items:
        fits = all(not names or _named(item, marker) & names for marker, names in wanted.items())
        (keep if fits else drop).append(item)
    if drop:
        config.hook.pytest_deselected(items=drop)
        items[:] = keep
