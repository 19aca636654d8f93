"""Which trials a run makes: counts, seeds, and shards.

Every scenario's trials are a plan: trial ``i`` gets the ``i``-th seed drawn
from a Random seeded by ``--seed`` and the test's node id, so any trial can
be replayed alone (``--trial-seed S``: one trial per scenario, seed S). A
scenario asks for ``quick`` trials by default, ``deep`` with ``--deep`` (or
CLONEGUARD_DEEP=1), exactly N with ``--trials N``.

``--shard K/N`` (one of N runs, on other cores, jobs or machines) makes the
trials ``i`` with ``i % N == K - 1``, with the seeds the unsharded run would
have given them: the N shards together make exactly the unsharded run's
trials, none twice, and ``python -m cloneguard.harness merge`` joins their reports. A
scenario none of whose trials falls to this shard is skipped.

Fixtures (registered by harness.pytest_plugin)
    trial_plan(quick, deep) -> [(index, seed), ...] for this run (skips the test if empty)
    record_trial(index, seed, Outcome)     one trial into the report
    run_trials(trial, settle, quick, deep) the loop most scenarios share; -> the
                                           whole run's trial count (all shards)
"""

from __future__ import annotations

import argparse
import os
import random
import zlib
from collections.abc import Callable
from typing import TYPE_CHECKING, Protocol

import pytest

from .errors import HarnessTimeout  # not .client: that imports rclpy

if TYPE_CHECKING:
    from .diagnose import Diagnosis
    from .report.record import Resilience
    from .rig import Outcome, Rig

    class RunTrials(Protocol):
        """What the ``run_trials`` fixture gives a test."""

        def __call__(
            self,
            trial: Callable[[int, int], Outcome],
            settle: Callable[[Outcome], object],
            quick: int,
            deep: int,
            *,
            rig: Rig | None = None,
        ) -> int: ...


ENV_DEEP = "CLONEGUARD_DEEP"
#: planned trials from which a scenario holds its deep floor (a 99% floor
#: judged on fewer cannot tell a 1% rate from chance)
DEEP_FLOOR_TRIALS = 100
#: per-test timeout of a deep run or one with --trials N (hundreds of trials
#: do not fit the quick runs' per-test timeouts)
LONG_RUN_TIMEOUT_S = 4 * 3600


def trial_count_arg(text: str) -> int:
    """A command line's trial count: a whole number, at least 1 (argparse
    turns the error into a usage error)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a trial count is a whole number, not {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"a trial count is at least 1, not {value}")
    return value


def add_options(parser: pytest.Parser) -> None:
    group = parser.getgroup("cloneguard trials")
    group.addoption(
        "--deep", action="store_true", default=False, help="run the deep trial counts (hundreds per scenario)"
    )
    group.addoption(
        "--trials", type=trial_count_arg, default=None, metavar="N", help="run exactly N (>= 1) trials per scenario"
    )
    group.addoption("--seed", type=int, default=1, help="base seed of every random choice (default 1)")
    group.addoption(
        "--trial-seed",
        type=int,
        default=None,
        metavar="S",
        help="run one trial per scenario, with this seed (a trial's seed, as its report shows it)",
    )


def parse_shard(text: str) -> tuple[int, int]:
    """ "K/N" -> (K, N), 1 <= K <= N."""
    try:
        k, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"--shard takes K/N (e.g. 3/8), not {text!r}") from None
    if not 1 <= k <= n:
        raise ValueError(f"--shard {text}: K must be between 1 and N")
    return k, n


def shard_of(config: pytest.Config) -> tuple[int, int] | None:
    text = config.getoption("--shard", default=None)
    return parse_shard(text) if text else None


def is_deep(config: pytest.Config) -> bool:
    """--deep, or CLONEGUARD_DEEP=1 in the environment."""
    return bool(config.getoption("--deep", default=False)) or os.environ.get(ENV_DEEP, "") == "1"


def trial_plan_of(config: pytest.Config) -> dict:
    """What decides which trials a run makes (runs merge only if equal)."""
    plan = {
        "seed": config.getoption("--seed", default=None),
        "deep": is_deep(config),
        "trials": config.getoption("--trials", default=None),
    }
    trial_seed = config.getoption("--trial-seed", default=None)
    if trial_seed is not None:  # a replay: merges only with the same replay
        plan["trial_seed"] = trial_seed
    return plan


def trial_count(config: pytest.Config, quick: int, deep: int) -> int:
    if config.getoption("--trial-seed", default=None) is not None:
        return 1
    forced = config.getoption("--trials")
    if forced is not None:
        return forced
    return deep if is_deep(config) else quick


def long_run(config: pytest.Config) -> bool:
    return is_deep(config) or config.getoption("--trials") is not None


def give_long_timeouts(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A deep run's tests get LONG_RUN_TIMEOUT_S (before any timeout marker
    of their own, which sized the quick run)."""
    if long_run(config):
        for item in items:
            item.add_marker(pytest.mark.timeout(LONG_RUN_TIMEOUT_S), append=False)


def plan(count: int, rng: random.Random, shard: tuple[int, int] | None) -> list[tuple[int, int]]:
    """(index, seed) of this shard's trials out of ``count``; the seeds are
    drawn for every index, so they do not depend on the shard."""
    out = []
    for i in range(count):
        seed = rng.getrandbits(31)
        if shard is None or i % shard[1] == shard[0] - 1:
            out.append((i, seed))
    return out


def scenario_rng(config: pytest.Config, nodeid: str) -> random.Random:
    """A Random seeded from --seed and the test's node id."""
    return random.Random(config.getoption("--seed") * 1_000_003 + zlib.crc32(nodeid.encode()))


@pytest.fixture
def trial_plan(request: pytest.FixtureRequest) -> Callable[[int, int], list[tuple[int, int]]]:
    def make(quick: int, deep: int) -> list[tuple[int, int]]:
        config = request.config
        shard = shard_of(config)
        count = trial_count(config, quick, deep)
        trial_seed = config.getoption("--trial-seed", default=None)
        if trial_seed is not None:  # one trial, replayed by its own seed
            planned = [(0, trial_seed)] if shard is None or shard[0] == 1 else []
        else:
            planned = plan(count, scenario_rng(config, request.node.nodeid), shard)
        if not planned:
            where = f"shard {shard[0]}/{shard[1]}" if shard else "this run"
            pytest.skip(f"{where} has none of this scenario's {count} trial(s)")
        return planned

    return make


@pytest.fixture
def record_trial(resilience: Resilience) -> Callable[[int, int, Outcome], None]:
    """record_trial(index, seed, Outcome): one trial into the report."""

    def record(index: int, seed: int, out: Outcome) -> None:
        resilience.trial(outcome=out.outcome, index=index, seed=seed, latency_ms=out.latency_ms, details=out.details)
        if out.diagnosis is not None:
            record_hang(resilience, index, out.diagnosis)

    return record


def record_hang(resilience: Resilience, index: int, d: Diagnosis) -> None:
    """A hung trial's diagnosis (diagnose.Diagnosis) into the report."""
    first = d.blocked[0] if d.blocked else None
    resilience.hang(
        trial=index,
        summary=d.summary(),
        stacks=d.stacks_text,
        lock=first.address if first else "",
        owner_tid=first.owner_tid if first else None,
        owner_node=first.owner_node if first else None,
    )


@pytest.fixture
def run_trials(
    request: pytest.FixtureRequest,
    record_trial: Callable[[int, int, Outcome], None],
    trial_plan: Callable[[int, int], list[tuple[int, int]]],
) -> RunTrials:
    """run_trials(trial, settle, quick, deep, rig=None): the trial loop every
    rate scenario shares: ``trial(seed, index) -> Outcome`` for each planned
    trial, recorded, then ``settle(outcome)`` (which replaces a broken
    container). With the trials' ``rig``, a trial whose own request goes
    unanswered is a hang of that rig (diagnosed), not an error of the
    scenario. Returns how many trials the whole run makes of the scenario,
    every shard's together: what decides which floor a scenario holds (a
    shard of a sharded deep run has a share of the trials, but the floor is
    judged on them all, by ``harness merge``)."""

    def run(
        trial: Callable[[int, int], Outcome],
        settle: Callable[[Outcome], object],
        quick: int,
        deep: int,
        *,
        rig: Rig | None = None,
    ) -> int:
        for i, seed in trial_plan(quick, deep):
            try:
                out = trial(seed, i)
            except HarnessTimeout as exc:
                if rig is None:
                    raise
                # A request of the trial's own went unanswered (a load, say):
                # the container is stuck, judged and diagnosed as any hang.
                out = rig.not_survived(f"the trial's request went unanswered: {exc}")
            record_trial(i, seed, out)
            settle(out)
        return trial_count(request.config, quick, deep)

    return run
