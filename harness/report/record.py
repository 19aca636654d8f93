"""What one test records for the crash-resilience report: the ``resilience``
fixture, and how the record reaches the process that writes the report.

Scenarios record through the fixture::

    def test_segfault_in_callback(resilience):
        resilience.describe(fault="segfault-gil-held", profile="per-node",
                            mitigations={"gil_repair": True},
                            claim="the container survives a SIGSEGV in one node's callback")
        for trial in range(20):
            ...
            resilience.trial("survived", seed=seed, latency_ms={"death_to_event": 0.4})
        resilience.expect_rate(TrialOutcome.SURVIVED, at_least=0.95)

The record lives in the process that runs the test (a pytest-xdist worker,
or the one pytest process). When the test's teardown report is made, the
record rides on it (``report.cloneguard_record``, plain JSON data, which
xdist carries to the controller like the rest of the report); the report
session (session.py) takes it from there.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Generator, Mapping
from datetime import UTC, datetime
from typing import Any

import pytest

from . import stats
from .model import CONTAINER_DEATH, TRIAL_OUTCOMES, Expectation, Hang, Scenario, Trial, TrialOutcome, jsonable

#: the report attribute that carries a test's record to the report session
RECORD_ATTR = "cloneguard_record"
#: How many of the trials that broke an expectation its failure names.
FIRST_AGAINST = 3
_RECORDERS = pytest.StashKey[dict]()


def _iso(ts: float) -> str:
    return datetime.fromtimestamp(ts, UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


# --------------------------------------------------------------------------
# The fixture's object
# --------------------------------------------------------------------------
class Resilience:
    """What one scenario records. Obtained through the ``resilience`` fixture."""

    def __init__(self, scenario: Scenario, *, defer: bool = False):
        self._scenario = scenario
        self._defer = defer  # a shard: expectations are judged by the merge
        self._lock = threading.Lock()

    @property
    def scenario(self) -> Scenario:
        """The record being filled (read it, do not change it)."""
        return self._scenario

    def describe(
        self,
        *,
        fault: str | None = None,
        profile: str | None = None,
        mitigations: Mapping[str, Any] | None = None,
        claim: str | None = None,
        name: str | None = None,
        units: Mapping[str, str] | None = None,
    ) -> None:
        """What the scenario is: the fault injected, the isolation profile, the
        mitigations switched on, and the claim it checks. Can be called again;
        arguments left out keep their value. ``name`` replaces the test name
        shown in the report. ``units``: series name -> the unit its
        ``trial(latency_ms=...)`` values are in, for series not in ms (added
        to those given before; a series keeps its first unit)."""
        with self._lock:
            s = self._scenario
            if fault is not None:
                s.fault = str(fault)
            if profile is not None:
                s.profile = str(profile)
            if mitigations is not None:
                if not isinstance(mitigations, Mapping):
                    raise TypeError(f"mitigations must be a mapping, got {type(mitigations).__name__}")
                s.mitigations = jsonable(dict(mitigations))
            if claim is not None:
                s.claim = str(claim)
            if name is not None:
                s.name = str(name)
            for series, unit in (units or {}).items():
                known = s.units.get(series, unit)
                if known != unit:
                    raise ValueError(f"series {series!r} is in {known}, not {unit}")
                s.units[str(series)] = str(unit)

    def trial(
        self,
        outcome: str,
        *,
        index: int | None = None,
        seed: Any = None,
        latency_ms: Mapping[str, float | list[float] | None] | None = None,
        details: Mapping[str, Any] | None = None,
    ) -> int:
        """Record one trial and return its index: ``index`` (its place in the
        scenario's plan, which a shard skips parts of), else the next one.

        outcome: a TrialOutcome (or its value; stored as the plain value, which
        is what report.json and pytest-xdist's channel carry); failed needs
        a why in ``details``.
        latency_ms: series name -> milliseconds (a number, a list of numbers,
        or None for "not measured").
        """
        if outcome not in TRIAL_OUTCOMES:
            raise ValueError(f"trial outcome must be one of {TRIAL_OUTCOMES}, got {outcome!r}")
        latencies = _check_latencies(latency_ms or {})
        if details is not None and not isinstance(details, Mapping):
            raise TypeError(f"details must be a mapping, got {type(details).__name__}")
        with self._lock:
            if index is None:
                index = self._scenario.trials[-1].index + 1 if self._scenario.trials else 0
            self._scenario.trials.append(
                Trial(
                    index=index,
                    outcome=TrialOutcome(outcome).value,
                    seed=jsonable(seed),
                    latency_ms=latencies,
                    details=jsonable(dict(details or {})),
                    time=_iso(time.time()),
                )
            )
        return index

    def hang(
        self,
        *,
        summary: str,
        trial: int | None = None,
        stacks: str | None = None,
        lock: Any = None,
        owner_tid: int | None = None,
        owner_node: str | None = None,
        details: Mapping[str, Any] | None = None,
    ) -> None:
        """Record the diagnosis of a hang: a one-line ``summary``, the trial it
        happened in, the threads' ``stacks`` (text), the ``lock`` waited on
        (an int is shown in hex) and who owns it."""
        if isinstance(lock, int) and not isinstance(lock, bool):
            lock = hex(lock)
        if lock == "":
            lock = None
        with self._lock:
            self._scenario.hangs.append(
                Hang(
                    summary=str(summary),
                    trial=trial,
                    stacks=None if stacks is None else str(stacks),
                    lock=None if lock is None else str(lock),
                    owner_tid=None if owner_tid is None else int(owner_tid),
                    owner_node=None if owner_node is None else str(owner_node),
                    details=jsonable(dict(details or {})),
                )
            )

    def counts(self) -> dict[str, int]:
        """Trials so far by outcome."""
        with self._lock:
            return self._scenario.counts()

    def rate(self, outcome: str = TrialOutcome.SURVIVED) -> stats.Proportion:
        """The measured rate of ``outcome`` so far, with its Wilson interval."""
        with self._lock:
            return self._scenario.rate_of(outcome)

    def expect_rate(
        self, outcome: str = TrialOutcome.SURVIVED, *, at_least: float | None = None, at_most: float | None = None
    ) -> Expectation:
        """Record the rate of ``outcome`` this profile promises and check it
        against the trials so far: raises AssertionError (with the counts)
        when the measured rate is below ``at_least`` or above ``at_most``, or
        when there are no trials. In a shard of a sharded run it is recorded
        unjudged: only all shards' trials together (``harness merge``) can
        keep or break it."""
        __tracebackhide__ = True
        if outcome not in TRIAL_OUTCOMES:
            raise ValueError(f"outcome must be one of {TRIAL_OUTCOMES}, got {outcome!r}")
        outcome = TrialOutcome(outcome).value
        if at_least is None and at_most is None:
            raise ValueError("expect_rate needs at_least or at_most")
        for bound in (at_least, at_most):
            if bound is not None and not 0.0 <= bound <= 1.0:
                raise ValueError(f"rates are between 0 and 1, got {bound!r}")
        with self._lock:
            counts = self._scenario.counts()
            expectation = Expectation.judged(
                outcome,
                at_least=at_least,
                at_most=at_most,
                successes=counts.get(outcome, 0),
                trials=len(self._scenario.trials),
                defer=self._defer,
            )
            self._scenario.expectations.append(expectation)
        if expectation.met is False:
            if expectation.rate is None:
                raise AssertionError(
                    f"expected {outcome} rate {expectation.requirement()}, but no trials were recorded"
                )
            raise AssertionError(
                f"expected {outcome} rate {expectation.requirement()}, measured {expectation.rate:.1%} "
                f"({expectation.successes}/{expectation.trials} trials {outcome}; 95% CI "
                f"{expectation.ci_low:.1%}–{expectation.ci_high:.1%}; counts {self.counts()})"
                + self._against(outcome, wanted=at_least is not None)
            )
        return expectation

    def _against(self, outcome: str, wanted: bool) -> str:
        """The first trials that broke an expectation on ``outcome`` (those
        that had another outcome if it was wanted, else those that had it),
        with their causes: what a CI log that shows only this line needs."""
        with self._lock:
            against = [t for t in self._scenario.trials if (t.outcome != outcome) == wanted]
        said = [
            f"trial {t.index} (seed {t.seed}) {t.outcome}" + (f": {t.details['why']}" if t.details.get("why") else "")
            for t in against[:FIRST_AGAINST]
        ]
        more = f"; {len(against) - FIRST_AGAINST} more" if len(against) > FIRST_AGAINST else ""
        return "; " + "; ".join(said) + more if said else ""

    def expect_no_container_death(self) -> Expectation:
        """The isolated cells' own floor, apart from any survival floor:
        none of the trials ended the container itself (every node at once).
        A cell whose survival floor allows a hang never allows that."""
        __tracebackhide__ = True
        return self.expect_rate(CONTAINER_DEATH, at_most=0.0)

    def note(self, text: str) -> None:
        """Free text shown with the scenario in the report."""
        with self._lock:
            self._scenario.notes.append(str(text))


def _check_latencies(latency_ms: Mapping) -> dict:
    if not isinstance(latency_ms, Mapping):
        raise TypeError(f"latency_ms must be a mapping of series name to ms, got {type(latency_ms).__name__}")
    out = {}
    for name, value in latency_ms.items():
        if value is None:
            continue
        values = value if isinstance(value, (list, tuple)) else [value]
        clean = []
        for v in values:
            if v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise TypeError(f"latency {name!r}: expected a number of ms, got {v!r}")
            v = float(v)
            if v != v or v in (float("inf"), float("-inf")):
                raise ValueError(f"latency {name!r}: not a finite number: {v!r}")
            clean.append(v)
        if not clean:
            continue
        out[str(name)] = clean if isinstance(value, (list, tuple)) else clean[0]
    return out


# --------------------------------------------------------------------------
# The fixture, and the hook that sends a record on with the teardown report
# --------------------------------------------------------------------------
def sharded(config: pytest.Config) -> bool:
    return bool(config.getoption("--shard", default=None))


@pytest.fixture
def resilience(request: pytest.FixtureRequest) -> Resilience:
    """Records a scenario's description, trials, hangs, expectations and notes
    for the crash-resilience report."""
    recorders = request.config.stash.setdefault(_RECORDERS, {})
    node = request.node
    recorder = recorders.get(node.nodeid)
    if recorder is None:
        scenario = Scenario(nodeid=node.nodeid, name=node.name, started=_iso(time.time()), used_resilience=True)
        recorder = recorders[node.nodeid] = Resilience(scenario, defer=sharded(request.config))
    return recorder


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(
    item: pytest.Item, call: pytest.CallInfo[None]
) -> Generator[None, pytest.TestReport, pytest.TestReport]:
    rep = yield
    if rep.when == "teardown":
        recorder = item.config.stash.get(_RECORDERS, {}).pop(item.nodeid, None)
        if recorder is not None:
            setattr(rep, RECORD_ATTR, recorder.scenario.to_dict())
    return rep
