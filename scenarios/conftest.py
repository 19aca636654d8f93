"""Shared glue for scenarios: trial counts, seeds, rigs, and recording.

Quick by default (a few trials per scenario, so `pytest scenarios/` fits CI);
`--deep` (or CLONEGUARD_DEEP=1) runs the deep counts, `--trials N` forces N.
"""
import os
import random
import zlib

import pytest

from harness.rig import Rig


def pytest_addoption(parser):
    group = parser.getgroup("cloneguard scenarios")
    group.addoption("--deep", action="store_true", default=False,
                    help="run the deep trial counts (hundreds per scenario)")
    group.addoption("--trials", type=int, default=None, help="run exactly N trials per scenario")
    group.addoption("--seed", type=int, default=1, help="base seed of every random choice (default 1)")


@pytest.fixture
def trials(request):
    """trials(quick, deep) -> the number of trials this run makes."""
    forced = request.config.getoption("--trials")
    deep = request.config.getoption("--deep") or os.environ.get("CLONEGUARD_DEEP") == "1"

    def count(quick: int, deep_count: int) -> int:
        return forced if forced is not None else (deep_count if deep else quick)

    return count


@pytest.fixture
def rng(request):
    """A Random seeded from --seed and the test's id: replayable per scenario."""
    base = request.config.getoption("--seed")
    return random.Random(base * 1_000_003 + zlib.crc32(request.node.nodeid.encode()))


@pytest.fixture
def rig_factory(container_factory):
    def make(profile: str, **kwargs) -> Rig:
        return Rig(container_factory, profile, **kwargs)
    return make


@pytest.fixture
def record_trial(resilience):
    """record_trial(index, seed, Outcome): one trial into the report."""
    def record(index: int, seed: int, out) -> None:
        resilience.trial(outcome=out.outcome, seed=seed, latency_ms=out.latency_ms, details=out.details)
        d = out.diagnosis
        if d is not None:
            first = d.blocked[0] if d.blocked else None
            resilience.hang(
                trial=index,
                summary=d.summary(),
                stacks=d.stacks_text,
                lock=first.address if first else "",
                owner_tid=first.owner_tid if first else None,
                owner_node=first.owner_node if first else None,
            )
    return record


@pytest.fixture
def run_trials(record_trial, trials, rng):
    """run_trials(trial, settle, quick, deep): the trial loop every rate
    scenario shares: a seed per trial, ``trial(seed, index) -> Outcome``,
    recorded, then ``settle(outcome)`` (which replaces a broken container)."""
    def run(trial, settle, quick: int, deep: int) -> None:
        for i in range(trials(quick, deep)):
            seed = rng.getrandbits(31)
            out = trial(seed, i)
            record_trial(i, seed, out)
            settle(out)
    return run
