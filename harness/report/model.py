"""The data of a crash-resilience report and its JSON form (report.json).

A :class:`Report` is one pytest run: :class:`RunInfo` and one
:class:`Scenario` per test. Scenarios hold what the test recorded (trials,
hang diagnoses, expectations, notes); everything statistical is derived from
the trials when needed, and also written to report.json (under ``stats`` and
``summary``) for readers that do not want to recompute it. Loading ignores
the derived parts, so report.json stays the single source of truth.
"""

from __future__ import annotations

import enum
import json
import math
import os
import tempfile
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from . import stats

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

    _D = TypeVar("_D", bound=DataclassInstance)

SCHEMA = "cloneguard-report/1"
REPORT_JSON = "report.json"
REPORT_HTML = "report.html"
JUNIT_XML = "junit.xml"


class TrialOutcome(enum.StrEnum):
    """What became of the container in one trial (a str: report.json holds
    the value)."""

    SURVIVED = "survived"  # the container and the other nodes are fine
    HUNG = "hung"  # the container, or a sibling, stopped making progress
    CRASHED = "crashed"  # the container process died
    FAILED = "failed"  # something else went wrong (the trial's details say what)
    CORRUPTED = "corrupted"  # a node's memory was changed by another and nothing noticed


#: The values, as records hold them (plain str).
TRIAL_OUTCOMES = tuple(o.value for o in TrialOutcome)
#: The outcome that is every node dying at once: the container process died.
#: Counted on its own, and shown first, wherever a report sums trials up.
CONTAINER_DEATH = TrialOutcome.CRASHED.value
#: Profiles of the thread-mode baselines, where a node's crash is the
#: container's by design: their container deaths are not counted as the
#: isolated cells' are.
BASELINE_PROFILES = ("threads",)
#: pytest's verdict on the test as a whole.
TEST_OUTCOMES = ("passed", "failed", "skipped", "error")


def jsonable(value: Any, _depth: int = 0) -> Any:
    """A copy of ``value`` that json.dumps accepts and that reads back the
    same: dict keys become strings, tuples and sets lists, bytes text,
    non-finite floats None, anything else its repr()."""
    if _depth > 50:
        return repr(value)
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): jsonable(v, _depth + 1) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v, _depth + 1) for v in value]
    if isinstance(value, (set, frozenset)):
        items = [jsonable(v, _depth + 1) for v in value]
        try:
            return sorted(items)
        except TypeError:
            return items
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return repr(value)


def _from(cls: type[_D], data: dict | None) -> _D:
    """Build dataclass ``cls`` from ``data``, ignoring unknown keys (newer or
    derived fields) and leaving missing ones at their defaults."""
    data = data or {}
    names = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in data.items() if k in names})


@dataclass
class Trial:
    index: int
    outcome: str
    seed: Any = None
    #: series name -> one value or a list of values, in the series' unit
    #: (Scenario.unit: milliseconds unless the scenario says otherwise)
    latency_ms: dict[str, Any] = field(default_factory=dict)
    details: dict[str, Any] = field(default_factory=dict)
    time: str | None = None

    @property
    def survived(self) -> bool:
        return self.outcome == TrialOutcome.SURVIVED

    def latency_values(self, series: str) -> list[float]:
        value = self.latency_ms.get(series)
        if value is None:
            return []
        if isinstance(value, list):
            return [float(v) for v in value if v is not None]
        return [float(value)]

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "outcome": self.outcome,
            "seed": self.seed,
            "latency_ms": self.latency_ms,
            "details": self.details,
            "time": self.time,
        }


@dataclass
class Hang:
    """The diagnosis of one hang: what the stuck container was waiting for."""

    summary: str
    trial: int | None = None
    stacks: str | None = None
    lock: str | None = None
    owner_tid: int | None = None
    owner_node: str | None = None
    details: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {
            "trial": self.trial,
            "summary": self.summary,
            "lock": self.lock,
            "owner_tid": self.owner_tid,
            "owner_node": self.owner_node,
            "stacks": self.stacks,
            "details": self.details,
        }


@dataclass
class Expectation:
    """A promised rate of one trial outcome and whether the measurement kept it."""

    outcome: str
    at_least: float | None = None
    at_most: float | None = None
    successes: int = 0
    trials: int = 0
    rate: float | None = None
    ci_low: float = 0.0
    ci_high: float = 1.0
    #: None: not judged in this run (a shard of a sharded run: the merge of
    #: all shards judges it, on all their trials)
    met: bool | None = False

    @classmethod
    def judged(
        cls,
        outcome: str,
        *,
        at_least: float | None,
        at_most: float | None,
        successes: int,
        trials: int,
        defer: bool = False,
    ) -> Expectation:
        """The expectation with its measurement: the rate, its 95% Wilson
        interval, and whether it was kept (None when ``defer``)."""
        p = stats.proportion(successes, trials)
        met = p.rate is not None
        if p.rate is not None and at_least is not None and p.rate < at_least:
            met = False
        if p.rate is not None and at_most is not None and p.rate > at_most:
            met = False
        return cls(
            outcome=outcome,
            at_least=at_least,
            at_most=at_most,
            successes=p.successes,
            trials=p.trials,
            rate=p.rate,
            ci_low=p.low,
            ci_high=p.high,
            met=None if defer else met,
        )

    def requirement(self) -> str:
        parts = []
        if self.at_least is not None:
            parts.append(f"≥ {self.at_least:.1%}")
        if self.at_most is not None:
            parts.append(f"≤ {self.at_most:.1%}")
        return " and ".join(parts)

    def to_dict(self) -> dict:
        return {
            "outcome": self.outcome,
            "at_least": self.at_least,
            "at_most": self.at_most,
            "successes": self.successes,
            "trials": self.trials,
            "rate": self.rate,
            "ci_low": self.ci_low,
            "ci_high": self.ci_high,
            "met": self.met,
        }


@dataclass
class Scenario:
    """One test of the run and everything it recorded."""

    nodeid: str
    name: str
    fault: str | None = None
    profile: str | None = None
    mitigations: dict[str, Any] = field(default_factory=dict)
    claim: str | None = None
    #: pytest's verdict: passed, failed, skipped or error (None: did not finish)
    outcome: str | None = None
    duration_s: float = 0.0
    started: str | None = None
    #: short failure/skip message, and the full failure text
    message: str | None = None
    longrepr: str | None = None
    used_resilience: bool = False
    #: series name -> the unit of its values, for series not in ms
    units: dict[str, str] = field(default_factory=dict)
    trials: list[Trial] = field(default_factory=list)
    hangs: list[Hang] = field(default_factory=list)
    expectations: list[Expectation] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    # -- derived ---------------------------------------------------------
    def counts(self) -> dict[str, int]:
        counts: dict[str, int] = {outcome: 0 for outcome in TRIAL_OUTCOMES}
        for trial in self.trials:
            counts[trial.outcome] = counts.get(trial.outcome, 0) + 1
        return counts

    def rate_of(self, outcome: str = TrialOutcome.SURVIVED) -> stats.Proportion:
        return stats.proportion(self.counts().get(outcome, 0), len(self.trials))

    def survival(self) -> stats.Proportion:
        return self.rate_of(TrialOutcome.SURVIVED)

    def container_deaths(self) -> stats.Proportion:
        return self.rate_of(CONTAINER_DEATH)

    @property
    def isolated(self) -> bool:
        """A cell of an isolated container (not a thread-mode baseline)."""
        return bool(self.profile) and (self.profile or "").split("/")[0] not in BASELINE_PROFILES

    def latency_series(self) -> dict[str, list[float]]:
        """Every latency series, in order of first appearance, with all values."""
        series: dict[str, list[float]] = {}
        for trial in self.trials:
            for name in trial.latency_ms:
                series.setdefault(name, []).extend(trial.latency_values(name))
        return series

    def unit(self, series: str) -> str:
        """The unit of a measured series' values."""
        return self.units.get(series, "ms")

    def latency_summaries(self) -> dict[str, stats.LatencySummary]:
        out = {}
        for name, values in self.latency_series().items():
            summary = stats.summarize(values)
            if summary is not None:
                out[name] = summary
        return out

    def expectations_met(self) -> bool:
        """No expectation judged and not kept (deferred ones do not count)."""
        return all(e.met is not False for e in self.expectations)

    def stats_dict(self) -> dict:
        return {
            "trials": len(self.trials),
            "counts": self.counts(),
            "survival": self.survival().to_dict(),
            "latency_ms": {k: v.to_dict() for k, v in self.latency_summaries().items()},
            "hangs": len(self.hangs),
            "expectations_met": self.expectations_met(),
        }

    def to_dict(self) -> dict:
        return {
            "nodeid": self.nodeid,
            "name": self.name,
            "fault": self.fault,
            "profile": self.profile,
            "mitigations": self.mitigations,
            "units": self.units,
            "claim": self.claim,
            "outcome": self.outcome,
            "duration_s": self.duration_s,
            "started": self.started,
            "message": self.message,
            "longrepr": self.longrepr,
            "used_resilience": self.used_resilience,
            "trials": [t.to_dict() for t in self.trials],
            "hangs": [h.to_dict() for h in self.hangs],
            "expectations": [e.to_dict() for e in self.expectations],
            "notes": list(self.notes),
            "stats": self.stats_dict(),
        }

    @classmethod
    def from_dict(cls, data: dict) -> Scenario:
        scenario = _from(cls, {k: v for k, v in data.items() if k not in ("trials", "hangs", "expectations")})
        scenario.mitigations = dict(scenario.mitigations or {})
        scenario.notes = list(scenario.notes or [])
        scenario.trials = [_from(Trial, t) for t in data.get("trials") or []]
        scenario.hangs = [_from(Hang, h) for h in data.get("hangs") or []]
        scenario.expectations = [_from(Expectation, e) for e in data.get("expectations") or []]
        return scenario


@dataclass
class RunInfo:
    id: str
    label: str | None = None
    started: str | None = None
    finished: str | None = None
    duration_s: float | None = None
    exit_status: int | None = None
    pytest_args: list[str] = field(default_factory=list)
    python: str | None = None
    host: dict[str, Any] = field(default_factory=dict)
    git: dict[str, Any] = field(default_factory=dict)
    #: the tested project (pyproject name, else its directory) and the
    #: versions of the stack and of every package declaring components
    project: str | None = None
    packages: dict[str, str] = field(default_factory=dict)
    container_exe: str | None = None
    deep: bool = False
    #: path of the JUnit XML, relative to the report directory when inside it
    junit: str | None = None
    #: who wrote junit.xml: "pytest", "pytest (--junitxml copied)", or "cloneguard"
    junit_writer: str | None = None
    #: pytest-xdist workers that ran the tests (0: none, one process)
    workers: int = 0
    #: what trials the run makes: base seed, deep, forced trial count; runs
    #: (shards) merge only when these are equal
    plan: dict[str, Any] = field(default_factory=dict)
    #: "K/N": this run is shard K of N of that plan
    shard: str | None = None
    #: a merged report: the runs it was made of (id, shard, host, commit, ...)
    shards: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass
class Report:
    run: RunInfo
    scenarios: list[Scenario] = field(default_factory=list)
    #: where the report was loaded from or saved to (not serialized)
    directory: Path | None = None

    def outcome_counts(self) -> dict[str, int]:
        counts = {outcome: 0 for outcome in TEST_OUTCOMES}
        for scenario in self.scenarios:
            key = scenario.outcome or "error"
            counts[key] = counts.get(key, 0) + 1
        return counts

    def summary(self) -> dict:
        trial_counts: dict[str, int] = {outcome: 0 for outcome in TRIAL_OUTCOMES}
        expectations = {"met": 0, "not_met": 0, "deferred": 0}
        for scenario in self.scenarios:
            for outcome, n in scenario.counts().items():
                trial_counts[outcome] = trial_counts.get(outcome, 0) + n
            for e in scenario.expectations:
                expectations[{True: "met", False: "not_met", None: "deferred"}[e.met]] += 1
        return {
            "tests": len(self.scenarios),
            "outcomes": self.outcome_counts(),
            "trials": sum(trial_counts.values()),
            "trial_outcomes": trial_counts,
            "container_deaths": self.container_deaths().to_dict(),
            "hangs": sum(len(s.hangs) for s in self.scenarios),
            "expectations": expectations,
        }

    def container_deaths(self) -> stats.Proportion:
        """Container deaths over every trial of the isolated cells."""
        cells = [s for s in self.scenarios if s.isolated]
        return stats.proportion(
            sum(s.counts().get(CONTAINER_DEATH, 0) for s in cells), sum(len(s.trials) for s in cells)
        )

    def to_dict(self) -> dict:
        return jsonable(
            {
                "schema": SCHEMA,
                "run": self.run.to_dict(),
                "summary": self.summary(),
                "scenarios": [s.to_dict() for s in self.scenarios],
            }
        )

    @classmethod
    def from_dict(cls, data: dict) -> Report:
        schema = data.get("schema", "")
        if not str(schema).startswith("cloneguard-report/"):
            raise ValueError(f"not a cloneguard report (schema {schema!r})")
        run = _from(RunInfo, data.get("run") or {"id": "?"})
        return cls(run=run, scenarios=[Scenario.from_dict(s) for s in data.get("scenarios") or []])

    def save_json(self, directory: Path) -> Path:
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        path = directory / REPORT_JSON
        write_atomic(path, json.dumps(self.to_dict(), indent=1, allow_nan=False) + "\n")
        self.directory = directory
        return path


def write_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file in the same directory."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def resolve_report_path(path: str | os.PathLike) -> Path:
    """The report.json that ``path`` names: the file itself, a report
    directory holding it, or a ``latest`` text file naming a run directory."""
    p = Path(path)
    if p.is_symlink():  # reports/latest: name the run it points to
        p = p.resolve()
    if p.is_dir():
        candidate = p / REPORT_JSON
        if candidate.is_file():
            return candidate
        raise FileNotFoundError(f"{p} has no {REPORT_JSON}")
    if p.is_file():
        if p.suffix == ".json":
            return p
        # reports/latest written as a text file where symlinks are not possible
        target = p.read_text(encoding="utf-8", errors="replace").strip()
        if target and "\n" not in target:
            return resolve_report_path(p.parent / target)
        raise ValueError(f"{p} is neither a report directory nor a report.json")
    raise FileNotFoundError(f"no such report: {p}")


def load_report(path: str | os.PathLike) -> Report:
    json_path = resolve_report_path(path)
    with open(json_path, encoding="utf-8") as fh:
        data = json.load(fh)
    report = Report.from_dict(data)
    report.directory = json_path.parent
    return report
