"""pytest plugin: the crash-resilience report of a run.

Tests record through the ``resilience`` fixture (record.py). At the end of a
session that ran scenarios (a test used ``resilience``, or ran from a
``scenarios/`` directory) the report session (session.py), which this
plugin registers, writes ``report.json``, ``report.html`` and ``junit.xml``
into the run's report directory and points ``reports/latest`` at it
(paths.py). Under pytest-xdist (``-n N``) the controller does this, once,
from what every worker's test reports carry.

Options
    --report-dir PATH   this run's report directory (also env CLONEGUARD_REPORT_DIR);
                        default: <repo>/reports/<UTC time>-<random>
    --run-label TEXT    a label shown in the report
    --shard K/N         run shard K of N of the scenarios' trials (see
                        harness/plan.py); merge the shards' reports with
                        ``python -m cloneguard.harness merge``
"""

from __future__ import annotations

import pytest

from ..plan import parse_shard
from .paths import ENV_REPORT_DIR
from .record import pytest_runtest_makereport, resilience  # noqa: F401 (the plugin's hook and fixture)
from .session import SCENARIO_DIRS_INI, ReportSession

_SESSION = pytest.StashKey[ReportSession]()


# --------------------------------------------------------------------------
# Module-level hooks
# --------------------------------------------------------------------------
def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("cloneguard-report", "cloneguard crash-resilience reports")
    group.addoption(
        "--report-dir",
        default=None,
        metavar="PATH",
        help=f"directory for this run's report.json, report.html and junit.xml "
        f"(env {ENV_REPORT_DIR}; default: <repo>/reports/<UTC time>-<random>)",
    )
    parser.addini(
        SCENARIO_DIRS_INI,
        "directories whose tests are scenarios, written in a report: names (any directory of that name) "
        "or paths from the pytest root directory; default: scenarios",
        type="linelist",
        default=[],
    )
    group.addoption("--run-label", default=None, metavar="TEXT", help="a label for this run, shown in the report")
    group.addoption(
        "--shard",
        default=None,
        metavar="K/N",
        help="run shard K of N of every scenario's trials (trial i where i %% N == K-1; seeds "
        "are drawn as in the unsharded run); merge the shards with `python -m cloneguard.harness merge`",
    )


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config: pytest.Config) -> None:
    shard = config.getoption("--shard", default=None)
    if shard:
        try:
            parse_shard(shard)
        except ValueError as exc:
            raise pytest.UsageError(str(exc)) from None
    # Before pytest's junitxml plugin reads --junitxml. Not on xdist workers.
    if hasattr(config, "workerinput"):
        return
    session = ReportSession(config)
    config.stash[_SESSION] = session
    session.configure_junit()
    config.pluginmanager.register(session, "cloneguard-report-session")


def pytest_unconfigure(config: pytest.Config) -> None:
    session = config.stash.get(_SESSION, None)
    if session is not None:
        config.pluginmanager.unregister(session)
        del config.stash[_SESSION]
