"""Seeded trials of your own System: the same fault and claims run again and
again, each outcome recorded in the crash-resilience report with what every
watched topic did and which faults were injected when, and a survival rate
with its interval judged at the end (docs/testing-your-nodes.md).

Public, and kept stable like ``system.py``: the ``system_trials`` fixture,
``SystemTrial`` and ``Measure``.

One trial is a call of your function with a ``SystemTrial`` (its index,
seed, a Random seeded from it, and when it started). Its outcome:

``survived``  it returned: every claim it asserts held;
``failed``    an assertion of yours did not hold (its message is the cause);
``hung``      something waited for did not come in time (a topic's
              messages, a CRASHED event, a node back): HarnessTimeout;
``crashed``   the container process itself died (every node at once).

After a trial the composition is brought back: the nodes a signal ended
are reloaded (or waited for, under ``--restart-policy on-crash``); after a
trial that did not survive, or every ``DEATHS_PER_CONTAINER`` node deaths,
the container is replaced with the whole composition loaded again.

Trial ``i`` gets the same seed in every run with the same ``--seed``
(plan.py), so ``--trials``, ``--deep``, ``--seed`` and ``--shard`` work on
your scenarios as on the project's, and sharded runs merge. To reproduce:
``--trial-seed S`` replays the one trial of seed S, ``--hold-failed``
stops at the first trial that does not survive and keeps its container
for a debugger, ``--container-arg`` adds container arguments.
"""

from __future__ import annotations

import math
import random
import signal
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple, Protocol

import pytest

from . import diagnose
from .cpu_starve import CpuStarveUnavailable
from .errors import HarnessTimeout
from .node_memory import series_ms
from .plan import record_hang
from .report.model import TrialOutcome

if TYPE_CHECKING:
    from .client import Recorder
    from .node_memory import MemorySample
    from .report.record import Resilience
    from .report.stats import Proportion
    from .system import Fault, System


class Drawable(Protocol):
    """What a timeline is drawn from: a System, or the rig's own."""

    @property
    def watched(self) -> Mapping[str, Recorder]: ...

    def memory_by_node(self, since_ns: int = 0, until_ns: int | None = None) -> dict[str, list[MemorySample]]: ...


#: A container is replaced after this many node deaths (each dead node
#: leaves its DDS participant behind: rig.DEATHS_PER_CONTAINER says why).
DEATHS_PER_CONTAINER = 100
#: How far before a trial the timeline looks for each node's last memory
#: report (container/diagnostics.py reports once a second).
MEMORY_LOOKBACK_NS = 1_500_000_000
#: Bins of a trial's timeline (the report's picture of each watched topic).
TIMELINE_BIN_MS = 100
#: How long a drawn trial's picture waits after the recovery for every
#: watched topic to speak again.
TIMELINE_TAIL_S = 2.0
HEARD_AGAIN = 3
#: Lines of a dead container's log kept with the trial.
CONTAINER_LOG_LINES = 40


@dataclass(frozen=True)
class SystemTrial:
    """What one trial is given: its place in the plan, its seed, a Random
    seeded from it (draw every random choice from it, so that the trial
    replays), and when it started (``time.monotonic_ns()``, the clock of
    ``System.kill`` and of the recorders)."""

    index: int
    seed: int
    rng: random.Random
    start_ns: int

    def pause(self, at_most_s: float) -> float:
        """Sleep a random time of up to ``at_most_s`` seconds (a fault at a
        random instant); how long."""
        if not 0 <= at_most_s <= 600:
            raise ValueError("pause for 0-600 s")
        seconds = self.rng.uniform(0.0, at_most_s)
        time.sleep(seconds)
        return seconds


class Measure(NamedTuple):
    """A trial's measurement in a unit other than milliseconds: return
    ``{"restarts": Measure(3, "count")}`` from a trial (a bare number is in
    ms). A series keeps the unit of its first trial."""

    value: float
    unit: str


def _measurements(measured: Mapping | None, resilience: Resilience) -> dict:
    """A trial's returned measurements as the report takes them: values,
    with the units of those not in ms told to the scenario."""
    if measured is None:
        return {}
    if not isinstance(measured, Mapping):
        raise TypeError(f"a trial returns a mapping of measurements (or None), not {type(measured).__name__}")
    units = {name: v.unit for name, v in measured.items() if isinstance(v, Measure)}
    if units:
        resilience.describe(units=units)
    return {name: v.value if isinstance(v, Measure) else v for name, v in measured.items()}


#: The participant profile of an isolated container started without
#: --profile: the container's (container/isolated/profiles.py), which the
#: harness, treating the container as a black box, does not import; a test
#: pins the two together.
DEFAULT_PROFILE = "shared"


def profile_of(container_args: Iterable[str]) -> str:
    """The report's profile of a container started with these arguments:
    ``threads`` without --isolated, else its participant profile."""
    args = list(container_args)
    if "--isolated" not in args:
        return "threads"
    for i, arg in enumerate(args):
        if arg == "--profile" and i + 1 < len(args):
            return args[i + 1]
        if arg.startswith("--profile="):
            return arg.split("=", 1)[1]
    return DEFAULT_PROFILE


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _outcome(system: System, exc: BaseException | None) -> tuple[str, str]:
    """(outcome, cause) of a trial that returned (exc None) or raised."""
    if not system.alive():
        return TrialOutcome.CRASHED.value, f"the container died (exit status {system.proc.wait(0)})"
    if exc is None:
        return TrialOutcome.SURVIVED.value, ""
    if isinstance(exc, HarnessTimeout):
        return TrialOutcome.HUNG.value, _first_line(exc)
    return TrialOutcome.FAILED.value, _first_line(exc)


def _window(rec: Recorder, start_ns: int, end_ns: int) -> list[int]:
    return [r.at_ns for r in rec.items() if start_ns <= r.at_ns <= end_ns]


def topic_facts(system: System, start_ns: int, end_ns: int) -> dict[str, dict]:
    """What each watched topic did between the two times: messages, rate
    (Hz) and longest gap (s, the window's edges counted)."""
    span = max(end_ns - start_ns, 1)
    out = {}
    for name, rec in system.watched.items():
        stamps = _window(rec, start_ns, end_ns)
        edges = [start_ns, *stamps, end_ns]
        gap = max(b - a for a, b in zip(edges, edges[1:], strict=False))
        out[name] = {
            "messages": len(stamps),
            "rate_hz": round(len(stamps) / (span / 1e9), 3),
            "longest_gap_s": round(gap / 1e9, 4),
        }
    return out


def fault_record(fault: Fault, start_ns: int) -> dict:
    """A fault as a trial records it: which node, what kind, what exactly,
    from when to when (ms from the trial's start)."""
    return {
        "node": fault.node,
        "kind": fault.kind,
        "what": fault.what,
        "from_ms": round((fault.start_ns - start_ns) / 1e6, 1),
        "to_ms": round((fault.end_ns - start_ns) / 1e6, 1),
    }


def timeline(system: Drawable, start_ns: int, end_ns: int) -> dict:
    """The trial and its recovery as the report draws them (with the
    trial's faults): messages per TIMELINE_BIN_MS bin of each watched
    topic, and each node's memory as its container reported it."""
    bin_ns = TIMELINE_BIN_MS * 1_000_000
    bins = max(1, (end_ns - start_ns) // bin_ns)  # whole bins: a cut one would read as a drop
    topics = {}
    for name, rec in system.watched.items():
        counts = [0] * bins
        for at in _window(rec, start_ns, start_ns + bins * bin_ns - 1):
            counts[(at - start_ns) // bin_ns] += 1
        topics[name] = counts
    drawn = {"bin_ms": TIMELINE_BIN_MS, "topics": topics}
    # From each node's last report before the trial (the container reports
    # once a second, and a trial may be shorter): a node killed early in
    # the trial has a strip too, ending where it died.
    before = system.memory_by_node(start_ns - MEMORY_LOOKBACK_NS, start_ns - 1)
    during = system.memory_by_node(start_ns, start_ns + bins * bin_ns)
    samples = {node: [*before.get(node, [])[-1:], *during.get(node, [])] for node in {*before, *during}}
    memory = series_ms(dict(sorted(samples.items())), start_ns)
    if memory:
        drawn["memory_mib"] = memory
    return drawn


def crash_reports(
    system: System, start_ns: int, end_ns: int, faults: Iterable[Fault], *, all_deaths: bool
) -> dict[str, str]:
    """The crash reports of the node processes that died in the trial (a
    CRASHED event between the two times), by "node (pid N)": of those that
    died on their own always, of those a fault of the trial ended only
    with ``all_deaths`` (a trial that did not survive). None are waited for
    from a dead container."""
    from cloneguard_interfaces.msg import ComponentEvent  # not at the plugin's import: no ROS then

    if not system.alive():
        return {}
    hit = {f.unique_id for f in faults if f.ends_the_node}
    out = {}
    for item in system.client.events.items():
        ev = item.msg
        if ev.event_type != ComponentEvent.CRASHED or not start_ns <= item.at_ns <= end_ns:
            continue
        if ev.unique_id in hit and not all_deaths:
            continue
        report = system.crash_report(ev.pid)
        if report:
            out[f"{ev.full_node_name} (pid {ev.pid})"] = report
    return out


#: The container's events a trial records among its facts (LOADED ones are
#: the harness's own reloads, after the trial).
TRIAL_EVENTS = ("CRASHED", "REPAIRED", "LOAD_FAILED", "UNLOADED")


def container_events(system: System, start_ns: int, end_ns: int) -> list[dict]:
    """The container's CRASHED, REPAIRED, LOAD_FAILED and UNLOADED events
    between the two times, in order: when (ms from ``start_ns``), which,
    of which node and process, and what it says. A REPAIRED's node and
    process are those of the node whose death left what was repaired; an
    event that leaves them out ('' and 0: the container's did, before its
    manager kept the names of its dead nodes) gets them from that node's
    own LOADED or CRASHED event, by its unique_id (a reload gets a new one)."""
    from .client import EVENT_NAMES  # imports the interfaces: not at the plugin's import

    items = system.client.events.items()
    named = {
        ev.unique_id: (ev.full_node_name, ev.pid)
        for ev in (i.msg for i in items)
        if EVENT_NAMES.get(ev.event_type) in ("LOADED", "CRASHED") and ev.unique_id and ev.full_node_name
    }
    out = []
    for item in items:
        ev = item.msg
        name = EVENT_NAMES.get(ev.event_type, str(ev.event_type))
        if name not in TRIAL_EVENTS or not start_ns <= item.at_ns <= end_ns:
            continue
        node, pid = (ev.full_node_name, ev.pid) if ev.full_node_name else named.get(ev.unique_id, ("", ev.pid))
        record = {"at_ms": round((item.at_ns - start_ns) / 1e6, 1), "event": name, "node": node, "pid": pid}
        if ev.repaired_state:
            record["repaired"] = ev.repaired_state
        if ev.error_message:
            record["what"] = ev.error_message
        out.append(record)
    return out


def _heard_again(system: System, within_s: float) -> None:
    """Until each watched topic has had HEARD_AGAIN messages more, or
    ``within_s``."""
    deadline = time.monotonic() + within_s
    for rec in system.watched.values():
        try:
            rec.wait_count(len(rec) + HEARD_AGAIN, timeout=max(0.0, deadline - time.monotonic()))
        except HarnessTimeout:
            return  # silent since: the picture shows it


def timeline_end(start_ns: int) -> int:
    """Now, once the timeline bin now falls in is whole (what arrived in
    it so far would read as a drop)."""
    bin_ns = TIMELINE_BIN_MS * 1_000_000
    end = start_ns + -(-(time.monotonic_ns() - start_ns) // bin_ns) * bin_ns
    time.sleep(max(0, end - time.monotonic_ns()) / 1e9)
    return end


def _settle(system: System, outcome: str, start_ns: int) -> None:
    """The composition whole again for the next trial."""
    if outcome == TrialOutcome.SURVIVED.value:
        try:
            system.recover(start_ns)
            if system.node_deaths() < DEATHS_PER_CONTAINER:
                return
        except HarnessTimeout:
            pass  # not back: a fresh container
    system.restart()


def run_system_trials(
    system: System,
    trial: Callable[[SystemTrial], Mapping | None],
    planned: Sequence[tuple[int, int]],
    resilience: Resilience,
    hold: Callable | None = None,
) -> None:
    """Each planned (index, seed) trial of ``system``, recorded. A trial
    may return a mapping of measurements (a series each): numbers in ms, or
    ``Measure(value, unit)``.
    With ``hold``, the first trial that does not survive is the last:
    ``hold(system, index, seed, cause)`` is called before anything is
    settled, with the container as the trial left it."""
    for index, seed in planned:
        start = time.monotonic_ns()
        first_fault = len(system.faults)
        exc: BaseException | None = None
        measured = None
        system.seed = seed  # what its message faults draw from
        try:
            measured = trial(SystemTrial(index, seed, random.Random(seed), start))
        except AssertionError as raised:  # HarnessTimeout is one
            exc = raised
        except CpuStarveUnavailable as missing:  # this machine cannot: said, not faked
            pytest.skip(f"CPU starvation is not possible here: {missing}")
        end = time.monotonic_ns()
        outcome, cause = _outcome(system, exc)
        faults = sorted(system.faults[first_fault:], key=lambda f: f.start_ns)  # in the order they began
        details: dict = {}
        if cause:
            details["why"] = cause
        details["faults"] = [fault_record(f, start) for f in faults]
        details["topics"] = topic_facts(system, start, end)
        if system.alive():
            details["events"] = container_events(system, start, end)
        reports = crash_reports(system, start, end, faults, all_deaths=outcome != TrialOutcome.SURVIVED.value)
        if reports:
            details["crash_reports"] = reports
        if outcome == TrialOutcome.HUNG.value:
            # What the container's threads were waiting on, as the project's
            # own scenarios get it: every stack, the lock and its holder.
            diagnosis = diagnose.of_container(system.proc, system.client)
            if diagnosis is not None:
                record_hang(resilience, index, diagnosis)
        if outcome == TrialOutcome.CRASHED.value:
            details["container_log"] = "\n".join(system.proc.log_text().splitlines()[-CONTAINER_LOG_LINES:])
        if hold is not None and outcome != TrialOutcome.SURVIVED.value:
            resilience.trial(
                outcome, index=index, seed=seed, latency_ms=_measurements(measured, resilience), details=details
            )
            hold(system, index, seed, f"{outcome}: {cause}")
            return
        try:
            _settle(system, outcome, start)
        finally:
            # The picture runs on through the recovery, until every watched
            # topic has spoken again (or TIMELINE_TAIL_S): the nodes back.
            if outcome != TrialOutcome.SURVIVED.value or index == planned[0][0]:
                _heard_again(system, TIMELINE_TAIL_S)
                details["timeline"] = timeline(system, start, timeline_end(start))
            resilience.trial(
                outcome, index=index, seed=seed, latency_ms=_measurements(measured, resilience), details=details
            )


def holder(config: pytest.Config, seconds: float) -> Callable:
    """What ``--hold-failed SECONDS`` does with a trial that did not
    survive: say where the container and its nodes are, on the terminal
    (past pytest's capture), and keep them that long (inf: until Ctrl-C)."""

    def hold(system: System, index: int, seed: int, cause: str) -> None:
        capture = config.pluginmanager.getplugin("capturemanager")
        with capture.global_and_fixture_disabled():
            print(f"\ntrial {index} (--trial-seed {seed}) did not survive: {cause}")
            print(f"container log: {system.proc.log_path}")
            if not system.alive():
                print("the container is gone: nothing to hold", flush=True)
                return
            nodes = ", ".join(f"{name} pid {r.pid}" for name, r in system.nodes.items())
            print(f"container pid {system.proc.pid} ({nodes})")
            if seconds == 0:
                print("not held (--hold-failed 0): stopping it now", flush=True)
                return
            print(f"attach a debugger:  gdb -p {system.proc.pid}    then: thread apply all bt")
            until = "Ctrl-C" if math.isinf(seconds) else f"{seconds:g} s"
            print(f"holding it until {until}", flush=True)
            try:
                if math.isinf(seconds):
                    signal.pause()
                else:
                    time.sleep(seconds)
            except KeyboardInterrupt:
                pass

    return hold


class SystemTrials:
    """What the ``system_trials`` fixture gives a test: called as
    ``system_trials(system, trial, *, fault, claim, quick=3, deep=200,
    at_least=None)``, it runs ``trial(SystemTrial)`` as seeded trials of
    ``system`` (``quick`` by default, ``deep`` with --deep, N with
    --trials N), records each in the report under ``fault`` and ``claim``,
    then, with ``at_least``, holds the survival rate to it (and, isolated,
    allows no container death). Returns the survival rate so far
    (``stats.Proportion``: successes, trials, rate, and its 95% interval low, high)."""

    def __init__(
        self,
        request: pytest.FixtureRequest,
        resilience: Resilience,
        trial_plan: Callable[[int, int], list[tuple[int, int]]],
    ):
        self._request, self._resilience, self._trial_plan = request, resilience, trial_plan

    def __call__(
        self,
        system: System,
        trial: Callable[[SystemTrial], Mapping | None],
        *,
        fault: str,
        claim: str,
        quick: int = 3,
        deep: int = 200,
        at_least: float | None = None,
    ) -> Proportion:
        __tracebackhide__ = True
        resilience = self._resilience
        resilience.describe(
            fault=fault,
            profile=profile_of(system.container_args),
            mitigations={"container args": " ".join(system.container_args) or "(none)"},
            claim=claim,
        )
        seconds = self._request.config.getoption("--hold-failed", default=None)
        hold = None if seconds is None else holder(self._request.config, seconds)
        run_system_trials(system, trial, self._trial_plan(quick, deep), resilience, hold)
        if at_least is not None:
            if profile_of(system.container_args) != "threads":
                resilience.expect_no_container_death()
            resilience.expect_rate(TrialOutcome.SURVIVED, at_least=at_least)
        return resilience.rate()


@pytest.fixture
def system_trials(
    request: pytest.FixtureRequest,
    resilience: Resilience,
    trial_plan: Callable[[int, int], list[tuple[int, int]]],
) -> SystemTrials:
    """A ``SystemTrials`` of this test (its docstring says what it does)."""
    return SystemTrials(request, resilience, trial_plan)
