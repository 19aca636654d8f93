"""SIGKILL in the middle of malloc/free, while blocks cross between nodes.

A hammer node allocates and frees without pause (16 B .. 1 MiB) and hands
one block in eight to a drain node that frees it, as a subscriber frees a
publisher's message. The hammer is SIGKILLed at a random instant, most
likely inside the allocator holding its arena lock. Measured per allocator:

glibc            per-thread arenas, non-robust locks, shared between tasks
jemalloc-auto    Debian's jemalloc preloaded, its own arena choice
jemalloc-own     jemalloc with an arena created for each node's process

Where an allocator is known to hang, the rate measured is what the report
says; the expectation recorded is the rate that allocator has shown, not a
promise of survival.
"""
import pytest

from faults.trials import MallocKill

ALLOCATORS = {
    "glibc": [],
    "jemalloc-auto": ["--jemalloc", "--jemalloc-arenas", "auto"],
    "jemalloc-own": ["--jemalloc", "--jemalloc-arenas", "own"],
}
# What each allocator has been measured to do (see the issue notes and the
# reports). jemalloc: a floor well under the measured rate, to catch
# regressions without flaking on 5 trials. glibc: a ceiling, because glibc
# malloc is known not to survive this (the dead task keeps its arena lock and
# the next free() of its blocks blocks for ever); if it ever starts to
# survive, this expectation is stale and should be revisited.
EXPECT = {
    "glibc": {"at_most": 0.8},
    "jemalloc-auto": {"at_least": 0.2},
    "jemalloc-own": {"at_least": 0.2},
}


@pytest.mark.timeout(360)      # 8 trials that mostly hang: ~15 s each to judge, diagnose, restart
@pytest.mark.parametrize("allocator", list(ALLOCATORS))
def test_sigkill_during_malloc(allocator, rig_factory, resilience, run_trials):
    resilience.describe(
        fault="sigkill-during-malloc", profile=f"per-node/{allocator}",
        mitigations={"allocator": allocator},
        claim=f"under {allocator}: a node SIGKILLed inside malloc/free while its blocks "
              "are freed by a sibling; does the container, the sibling and new nodes go on?",
    )
    fault = MallocKill(rig_factory("per-node", extra_args=ALLOCATORS[allocator]))
    # A ceiling needs more trials than a floor not to flake: glibc has
    # survived 0-3 of 5 in single runs (7 of 45 trials over nine runs).
    run_trials(fault.trial, fault.settle, quick=8 if "at_most" in EXPECT[allocator] else 5, deep=300)
    resilience.expect_rate("survived", **EXPECT[allocator])
