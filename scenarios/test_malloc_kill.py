"""SIGKILL in the middle of malloc/free, while blocks cross between nodes.

A hammer node allocates and frees without pause (16 B .. 2 MiB) and hands
one block in eight to a drain node that frees it, as a subscriber frees a
publisher's message. The hammer is SIGKILLed at a random instant, most
likely inside the allocator holding its arena's locks.

With the allocator guard (the default in isolated mode) the drain never
frees into the hammer's arena (blocks go back to their owner, and a dead
owner's arena is quarantined), under glibc and under jemalloc alike. The
baselines run the same fault with the guard switched off.
"""

import pytest

from cloneguard.faults.trials import FAULTS
from cloneguard.faults.trials import MALLOC_ALLOCATORS as ALLOCATORS
from cloneguard.harness.rig import TrialOutcome

# Guarded: 299/300 with glibc and with jemalloc in deep runs
# (docs/evidence.md). 28 of 30 is a floor a 99% rate breaks once in ~300
# runs (binomial tail), and that the unguarded allocators miss by far.
# Unguarded glibc hangs about half the time (111/200 survived: the dead
# hammer keeps its arena lock and the drain frees into that arena): a
# ceiling, so that a change that makes it survive is noticed, judged only
# on CEILING_MIN_TRIALS or more (on 8 trials a 55% rate passes 80% in 7% of
# runs). Unguarded jemalloc with an arena per node: 184/200, recorded, not
# promised.
EXPECT = {
    "glibc": {"at_least": 0.93},
    "jemalloc": {"at_least": 0.93},
    "glibc-unguarded": {"at_most": 0.8},
    "jemalloc-own-unguarded": None,
}
CEILING_MIN_TRIALS = 100
QUICK = {"glibc": 30, "jemalloc": 30, "glibc-unguarded": 8, "jemalloc-own-unguarded": 8}
# The unguarded baselines hang often (~15 s each to judge, diagnose and
# restart): 200 deep trials, the floor for every isolated-mode cell.
DEEP = {"glibc": 300, "jemalloc": 300, "glibc-unguarded": 200, "jemalloc-own-unguarded": 200}


@pytest.mark.timeout(360)  # unguarded trials mostly hang: ~15 s each to judge, diagnose, restart
@pytest.mark.parametrize("allocator", list(ALLOCATORS))
def test_sigkill_during_malloc(allocator, rig_factory, resilience, run_trials):
    guarded = "unguarded" not in allocator
    resilience.describe(
        fault="sigkill-during-malloc",
        profile=f"per-node/{allocator}",
        mitigations={"allocator": allocator.replace("-unguarded", ""), "alloc_guard": guarded},
        claim=f"under {allocator}: a node SIGKILLed inside malloc/free while its blocks "
        "are freed by a sibling; does the container, the sibling and new nodes go on?",
    )
    fault = FAULTS["sigkill-during-malloc"](rig_factory("per-node", extra_args=ALLOCATORS[allocator]))
    run_trials(fault.trial, fault.settle, quick=QUICK[allocator], deep=DEEP[allocator], rig=fault.rig)
    expect = EXPECT[allocator]
    if guarded:
        resilience.expect_no_container_death()
    if expect is None:
        resilience.note("baseline: survival measured, not promised")
    elif "at_most" in expect and len(resilience.scenario.trials) < CEILING_MIN_TRIALS:
        resilience.note(f"baseline: its ceiling is judged on {CEILING_MIN_TRIALS} trials or more (--deep)")
    else:
        resilience.expect_rate(TrialOutcome.SURVIVED, **expect)
    if guarded:
        quarantined = sum(1 for t in resilience.scenario.trials if t.details.get("allocator_quarantined"))
        resilience.note(
            f"{quarantined} of {len(resilience.scenario.trials)} hammers died inside "
            "the allocator (their arenas quarantined)"
        )
