"""Crash-resilience reports of scenario runs.

    collect   the pytest plugin: its options and hooks, the ``resilience`` fixture
    session   the report session: every test's outcome, the report written at the end
    paths     where reports go: the reports root, a run's directory name, ``latest``
    model     the report's data and report.json
    stats     Wilson intervals, the z-test, latency summaries
    render    report.html (self-contained: inline CSS and SVG)
    charts    the SVG charts
    system_view  a user's System's trials: per node and fault, per topic, the timeline, facts in words
    record    what one test records: the ``resilience`` fixture
    compare   comparison of two runs (``python -m cloneguard.harness compare``)
    merge     one report from the shards of a run and runs of other seeds (``python -m cloneguard.harness merge``)
    junit     junit.xml where pytest's own writer did not write one (a merge)
    summary   a report as Markdown (``python -m cloneguard.harness summary``)
    env       host and git facts for the run metadata

Only ``collect``, ``session`` and ``record`` import pytest; the rest is the
standard library.
"""

from .model import Report, Scenario, load_report

__all__ = ["Report", "Scenario", "load_report"]
