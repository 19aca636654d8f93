"""A node that leaks memory until it runs out.

In an isolated container every node process shares one address space, and
so does the kernel's OOM killer: when the container's memory cgroup is
full it ends every process of that address space, the whole container.
Two mitigations end the leaking node alone before that (issue 40):

- its budget (the LoadNode extra argument ``cloneguard.memory_limit``, or
  ``--node-memory-limit``): the node ends itself just before the allocation
  that would take it over, while the container still has room;
- without one, the container's memory watch: near the cgroup's limit it
  ends the node process that uses the most.

Each trial leaks one kind of memory, drawn from its seed: Python objects,
native malloc, one huge allocation (1.5 times what the container may use), a
bytearray. Survived: the leak alone was reported CRASHED with the
out-of-memory reason of its cause, the container goes on, the survivor's
50 Hz heartbeat never paused over a second, and the kernel's OOM killer
never acted (the cgroup's own count). Thread mode is the baseline: a budget
is refused there (one process), and the same leak ends the container.

Every container here runs in a memory cgroup of the harness's own making
with a limit (``Rig(memory_limit=...)``: 512 MiB), never against the
machine's memory; where none can be made the scenarios are skipped, saying
why. What only the dead leak reached is let go of (reclaim.py): each trial
records the container's memory before the load and after, and the report
notes how much stayed, by kind (a native leak's does). Trials share a
container until it has no room left for another budget above the watch's
margin; then, as after a trial that did not survive, the rig replaces it,
the new one born in a fresh cgroup (the old one removed with it).
"""

import statistics
from collections import Counter

import pytest

from cloneguard.faults.trials import (
    FAULTS,
    MALLOC_ALLOCATORS,
    OOM_BUDGET,
    OOM_CGROUP_LIMIT,
    OOM_DIAGNOSTICS_PERIOD_S,
    MiB,
)
from cloneguard.harness.memory_cgroup import MemoryCgroupUnavailable
from cloneguard.harness.plan import DEEP_FLOOR_TRIALS
from cloneguard.harness.rig import TrialOutcome

BUDGET = "out-of-memory/over-its-budget"
WATCH = "out-of-memory/container-full"
# Every leak ended alone (deep: 99%; quick runs: all 3).
FLOOR = 0.99
ROWS = {
    f"{profile}/{name}": (profile, args)
    for name, args in MALLOC_ALLOCATORS.items()
    if name in ("glibc", "jemalloc")
    for profile in ("per-node", "shared")
}
CLAIMS = {
    BUDGET: f"a node leaking past its own budget ({OOM_BUDGET // MiB} MiB, cloneguard.memory_limit) while the "
    "container has room ends itself alone: CRASHED 'out of memory: N MiB in use, over its limit', the rest "
    "goes on without a pause over 1 s, no kernel OOM kill",
    WATCH: f"a node with no budget leaking until its container nears its memory cgroup's limit "
    f"({OOM_CGROUP_LIMIT // MiB} MiB) is ended alone by the memory watch: CRASHED 'out of memory: the container "
    "used N MiB of the M MiB it may use, and this node process the most', the rest goes on without a pause "
    "over 1 s, no kernel OOM kill",
}


def _rig(rig_factory, profile: str, args):
    try:
        return rig_factory(
            profile, extra_args=args, memory_limit=OOM_CGROUP_LIMIT, diagnostics_period_s=OOM_DIAGNOSTICS_PERIOD_S
        )
    except MemoryCgroupUnavailable as why:
        pytest.skip(f"no memory cgroup can be made here: {why}")


def _note_kinds(resilience) -> None:
    """Which leaks the trials drew, how each kind fared, and how much of
    the container's memory stayed after each death (median by kind)."""
    by_kind: Counter = Counter()
    survived: Counter = Counter()
    kept: dict[str, list[float]] = {}
    for t in resilience.scenario.trials:
        kind = t.details.get("leak")
        by_kind[kind] += 1
        survived[kind] += t.outcome == TrialOutcome.SURVIVED
        if "kept_mib" in t.details:
            kept.setdefault(kind, []).append(t.details["kept_mib"])
    resilience.note(
        "leaks: " + ", ".join(f"{kind} {survived[kind]}/{n} survived" for kind, n in sorted(by_kind.items()))
    )
    if kept:
        resilience.note(
            "the container's memory after the leak's death, over what it was before its load (median MiB, "
            "trials; what only the dead leak reached is let go of, a native leak's stays): "
            + ", ".join(f"{kind} {statistics.median(mib):+.0f} ({len(mib)})" for kind, mib in sorted(kept.items()))
        )


@pytest.mark.timeout(180)
@pytest.mark.parametrize("fault", [BUDGET, WATCH], ids=["over-its-budget", "container-full"])
@pytest.mark.parametrize("row", list(ROWS))
def test_a_leaking_node_is_ended_alone(fault, row, rig_factory, resilience, run_trials):
    profile, args = ROWS[row]
    resilience.describe(
        fault=fault,
        profile=row,
        mitigations={
            "allocator": row.split("/")[1],
            "memory_budget": fault == BUDGET,
            "memory_watch": True,
        },
        claim=CLAIMS[fault],
    )
    trials = FAULTS[fault](_rig(rig_factory, profile, args))
    planned = run_trials(trials.trial, trials.settle, quick=3, deep=200, rig=trials.rig)
    _note_kinds(resilience)
    resilience.expect_no_container_death()
    resilience.expect_rate(TrialOutcome.SURVIVED, at_least=FLOOR if planned >= DEEP_FLOOR_TRIALS else 1.0)


@pytest.mark.timeout(120)
@pytest.mark.parametrize("fault", [BUDGET, WATCH], ids=["over-its-budget", "container-full"])
def test_thread_mode_loses_the_whole_container(fault, rig_factory, resilience, run_trials):
    """The baseline: in thread mode nothing but the kernel's OOM killer ends
    a leak, and it ends the container."""
    resilience.describe(
        fault=fault,
        profile="threads/glibc",
        mitigations={"memory_budget": False, "memory_watch": False},
        claim="baseline: in thread mode "
        + ("a node's budget is refused (one process), and " if fault == BUDGET else "")
        + f"a node leaking until the container's memory cgroup ({OOM_CGROUP_LIMIT // MiB} MiB) is full ends the "
        "whole container: the kernel's OOM killer ends its one process",
    )
    trials = FAULTS[fault](_rig(rig_factory, "threads", []))
    run_trials(trials.trial, trials.settle, quick=3, deep=20, rig=trials.rig)
    _note_kinds(resilience)
    resilience.expect_rate(TrialOutcome.CRASHED, at_least=1.0)
    kills = [t.details.get("oom_kills", 0) for t in resilience.scenario.trials]
    assert all(kills), f"the kernel's OOM kills per trial: {kills}"
    if fault == BUDGET:
        refused = [t.details.get("budget", "") for t in resilience.scenario.trials]
        assert all(r.startswith("refused: ") for r in refused), refused
