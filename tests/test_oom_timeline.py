"""The project's own out-of-memory trials (faults/trials.py, the rig's)
draw each node's memory in the report: their containers report it ten
times a second (``diagnostic_updater.period``), and a leak lasts about a
second. A real leak, in a memory cgroup this test made."""

from __future__ import annotations

import pytest

from cloneguard.faults.trials import FAULTS, OOM_CGROUP_LIMIT, OOM_DIAGNOSTICS_PERIOD_S, MiB
from cloneguard.harness.memory_cgroup import MemoryCgroupUnavailable
from cloneguard.harness.report.model import Scenario, Trial
from cloneguard.harness.report.system_view import has_system_view, timeline
from cloneguard.harness.rig import Rig, TrialOutcome

PYTHON_SEED = 0  # OutOfMemory draws its leak from the seed: this one's Python objects, the slowest


def test_a_leak_that_fills_the_container_is_drawn_rising_then_ended(container_factory):
    try:
        rig = Rig(
            container_factory, "shared", memory_limit=OOM_CGROUP_LIMIT, diagnostics_period_s=OOM_DIAGNOSTICS_PERIOD_S
        )
    except MemoryCgroupUnavailable as why:
        pytest.skip(f"no memory cgroup can be made here: {why}")
    trials = FAULTS["out-of-memory/container-full"](rig)
    out = trials.trial(PYTHON_SEED, 0)
    assert out.outcome == TrialOutcome.SURVIVED and out.details["leak"] == "python", out.details
    drawn = out.details["timeline"]
    assert sum(drawn["topics"]["/survivor/heartbeat"]) > 0
    leak = [mib for _, mib in drawn["memory_mib"]["/leak0"]]
    # It rose, report by report, until the watch ended it near the limit
    # (its memory as the guard counts it, below the cgroup's use).
    assert len(leak) >= 3 and leak == sorted(leak) and 100 <= leak[-1] < OOM_CGROUP_LIMIT / MiB, leak
    assert drawn["memory_mib"]["/survivor"]  # the rest drawn beside it
    scenario = Scenario(nodeid="t", name="t", trials=[Trial(0, out.outcome, seed=PYTHON_SEED, details=out.details)])
    assert has_system_view(scenario) and "/leak0 memory" in timeline(scenario)
