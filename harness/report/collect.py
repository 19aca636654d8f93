"""pytest plugin: the ``resilience`` fixture, and the report of the run.

Scenarios record what happened through the fixture::

    def test_segfault_in_callback(resilience):
        resilience.describe(fault="segfault-gil-held", profile="per-node",
                            mitigations={"gil_repair": True},
                            claim="the container survives a SIGSEGV in one node's callback")
        for trial in range(20):
            ...
            resilience.trial("survived", seed=seed, latency_ms={"death_to_event": 0.4})
        resilience.expect_rate("survived", at_least=0.95)

At the end of a session that ran scenarios (a test used ``resilience``, or
ran from a ``scenarios/`` directory) it writes ``report.json``,
``report.html`` and ``junit.xml`` into the run's report directory and
points ``reports/latest`` at it.

Options
    --report-dir PATH   this run's report directory (also env CLONEGUARD_REPORT_DIR);
                        default: <repo>/reports/<UTC time>-<random>
    --run-label TEXT    a label shown in the report
"""
from __future__ import annotations

import os
import secrets
import shutil
import threading
import time
import traceback
import xml.etree.ElementTree as ET
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Mapping

import pytest

from . import env, stats
from .model import (
    JUNIT_XML, REPORT_HTML, TRIAL_OUTCOMES, Expectation, Hang, Report, RunInfo, Scenario, Trial,
    jsonable, write_atomic,
)
from .render import write_html

ENV_REPORT_DIR = "CLONEGUARD_REPORT_DIR"
ENV_DEEP = "CLONEGUARD_DEEP"
SCENARIO_DIR = "scenarios"
LATEST = "latest"
#: longest pytest failure text kept per test
LONGREPR_LIMIT = 40_000


def repo_root() -> Path:
    """The directory holding pyproject.toml next to harness/ (for an
    installed, not editable, copy: the current directory)."""
    root = Path(__file__).resolve().parents[2]
    if (root / "pyproject.toml").is_file() and (root / "harness").is_dir():
        return root
    return Path.cwd()


def default_reports_root() -> Path:
    return repo_root() / "reports"


def new_run_id(now: datetime | None = None) -> str:
    now = now or datetime.now(timezone.utc)
    return now.strftime("%Y%m%dT%H%M%SZ") + "-" + secrets.token_hex(2)


def _iso(ts: float) -> str:
    return datetime.fromtimestamp(ts, timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z")


# --------------------------------------------------------------------------
# The fixture's object
# --------------------------------------------------------------------------
class Resilience:
    """What one scenario records. Obtained through the ``resilience`` fixture."""

    def __init__(self, scenario: Scenario):
        self._scenario = scenario
        self._lock = threading.Lock()

    @property
    def scenario(self) -> Scenario:
        """The record being filled (read it, do not change it)."""
        return self._scenario

    def describe(self, *, fault: str | None = None, profile: str | None = None,
                 mitigations: Mapping[str, Any] | None = None, claim: str | None = None,
                 name: str | None = None) -> None:
        """What the scenario is: the fault injected, the isolation profile, the
        mitigations switched on, and the claim it checks. Can be called again;
        arguments left out keep their value. ``name`` replaces the test name
        shown in the report."""
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

    def trial(self, outcome: str, *, seed: Any = None,
              latency_ms: Mapping[str, float | list[float] | None] | None = None,
              details: Mapping[str, Any] | None = None) -> int:
        """Record one trial and return its index (0, 1, ...).

        outcome: survived (container and other nodes fine), hung (container
        stopped making progress), crashed (container process died) or failed
        (something else went wrong; say what in ``details``).
        latency_ms: series name -> milliseconds (a number, a list of numbers,
        or None for "not measured").
        """
        if outcome not in TRIAL_OUTCOMES:
            raise ValueError(f"trial outcome must be one of {TRIAL_OUTCOMES}, got {outcome!r}")
        latencies = _check_latencies(latency_ms or {})
        if details is not None and not isinstance(details, Mapping):
            raise TypeError(f"details must be a mapping, got {type(details).__name__}")
        with self._lock:
            index = len(self._scenario.trials)
            self._scenario.trials.append(Trial(
                index=index, outcome=outcome, seed=jsonable(seed), latency_ms=latencies,
                details=jsonable(dict(details or {})), time=_iso(time.time()),
            ))
        return index

    def hang(self, *, summary: str, trial: int | None = None, stacks: str | None = None,
             lock: Any = None, owner_tid: int | None = None, owner_node: str | None = None,
             details: Mapping[str, Any] | None = None) -> None:
        """Record the diagnosis of a hang: a one-line ``summary``, the trial it
        happened in, the threads' ``stacks`` (text), the ``lock`` waited on
        (an int is shown in hex) and who owns it."""
        if isinstance(lock, int) and not isinstance(lock, bool):
            lock = hex(lock)
        if lock == "":
            lock = None
        with self._lock:
            self._scenario.hangs.append(Hang(
                summary=str(summary), trial=trial, stacks=None if stacks is None else str(stacks),
                lock=None if lock is None else str(lock),
                owner_tid=None if owner_tid is None else int(owner_tid),
                owner_node=None if owner_node is None else str(owner_node),
                details=jsonable(dict(details or {})),
            ))

    def counts(self) -> dict[str, int]:
        """Trials so far by outcome."""
        with self._lock:
            return self._scenario.counts()

    def rate(self, outcome: str = "survived") -> stats.Proportion:
        """The measured rate of ``outcome`` so far, with its Wilson interval."""
        with self._lock:
            return self._scenario.rate_of(outcome)

    def expect_rate(self, outcome: str = "survived", *, at_least: float | None = None,
                    at_most: float | None = None) -> Expectation:
        """Record the rate of ``outcome`` this profile promises and check it
        against the trials so far: raises AssertionError (with the counts)
        when the measured rate is below ``at_least`` or above ``at_most``, or
        when there are no trials."""
        __tracebackhide__ = True
        if outcome not in TRIAL_OUTCOMES:
            raise ValueError(f"outcome must be one of {TRIAL_OUTCOMES}, got {outcome!r}")
        if at_least is None and at_most is None:
            raise ValueError("expect_rate needs at_least or at_most")
        for bound in (at_least, at_most):
            if bound is not None and not 0.0 <= bound <= 1.0:
                raise ValueError(f"rates are between 0 and 1, got {bound!r}")
        with self._lock:
            p = self._scenario.rate_of(outcome)
            met = p.rate is not None
            if met and at_least is not None and p.rate < at_least:
                met = False
            if met and at_most is not None and p.rate > at_most:
                met = False
            expectation = Expectation(
                outcome=outcome, at_least=at_least, at_most=at_most, successes=p.successes,
                trials=p.trials, rate=p.rate, ci_low=p.low, ci_high=p.high, met=met,
            )
            self._scenario.expectations.append(expectation)
        if not met:
            if p.rate is None:
                raise AssertionError(f"expected {outcome} rate {expectation.requirement()}, but no trials were recorded")
            raise AssertionError(
                f"expected {outcome} rate {expectation.requirement()}, measured {p.rate:.1%} "
                f"({p.successes}/{p.trials} trials {outcome}; 95% CI {p.low:.1%}–{p.high:.1%}; "
                f"counts {self.counts()})"
            )
        return expectation

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
# The session
# --------------------------------------------------------------------------
_SESSION = pytest.StashKey["ReportSession"]()


def _under_scenarios(path: Path, root: Path) -> bool:
    try:
        parts = path.resolve().relative_to(root.resolve()).parts
    except ValueError:
        parts = path.resolve().parts
    return SCENARIO_DIR in parts[:-1] if path.suffix else SCENARIO_DIR in parts


def _args_run_scenarios(config) -> bool:
    """Whether the command line names a scenarios/ directory, a file in one,
    or a directory holding one."""
    base = Path(config.invocation_params.dir)
    for arg in config.args:
        text = str(arg).split("::", 1)[0]
        if not text or text.startswith("-"):
            continue
        path = (base / text)
        if _under_scenarios(path, Path(config.rootpath)) or path.name == SCENARIO_DIR:
            return True
        if path.is_dir() and (path / SCENARIO_DIR).is_dir():
            return True
    return False


class ReportSession:
    """Collects one Scenario per test and writes the report at the end."""

    def __init__(self, config):
        self.config = config
        self.started = time.time()
        self.records: dict[str, Scenario] = {}
        self.recorders: dict[str, Resilience] = {}
        self.reports_root = default_reports_root()
        option_dir = config.getoption("--report-dir", default=None)
        chosen = option_dir or os.environ.get(ENV_REPORT_DIR) or None
        if chosen:
            path = Path(os.path.expanduser(chosen))
            if not path.is_absolute():
                path = Path(config.invocation_params.dir) / path
            self.run_dir = path
            self.run_id = path.name
        else:
            self.run_id = new_run_id(datetime.fromtimestamp(self.started, timezone.utc))
            self.run_dir = self.reports_root / self.run_id
        self.explicit_dir = bool(chosen)
        self.junit_mode: str | None = None
        self.user_junit: Path | None = None
        self.written: Path | None = None
        self.error: str | None = None

    # -- setup -----------------------------------------------------------
    def configure_junit(self) -> None:
        """Send pytest's own JUnit writer to the report directory, unless the
        user chose a file. Decided now, before pytest's junitxml plugin
        configures itself: when the command line names no scenarios and no
        report directory, the report's junit.xml (if a report is written at
        all) is written by this plugin instead."""
        xmlpath = getattr(self.config.option, "xmlpath", None)
        if xmlpath:
            self.junit_mode = "user"
            self.user_junit = Path(os.path.abspath(os.path.expanduser(xmlpath)))
        elif self.explicit_dir or _args_run_scenarios(self.config):
            self.config.option.xmlpath = str(self.run_dir / JUNIT_XML)
            self.junit_mode = "pytest"

    # -- recording -------------------------------------------------------
    def _record(self, item) -> Scenario:
        record = self.records.get(item.nodeid)
        if record is None:
            record = Scenario(nodeid=item.nodeid, name=item.name, started=_iso(time.time()))
            self.records[item.nodeid] = record
        return record

    def recorder_for(self, item) -> Resilience:
        recorder = self.recorders.get(item.nodeid)
        if recorder is None:
            record = self._record(item)
            record.used_resilience = True
            recorder = Resilience(record)
            self.recorders[item.nodeid] = recorder
        return recorder

    def _in_scope(self, item) -> bool:
        if item.nodeid in self.records:
            return True
        if "resilience" in getattr(item, "fixturenames", ()):
            return True
        path = getattr(item, "path", None)
        return path is not None and _under_scenarios(Path(path), Path(self.config.rootpath))

    @pytest.hookimpl(wrapper=True)
    def pytest_runtest_makereport(self, item, call):
        rep = yield
        try:
            if self._in_scope(item):
                self._update(self._record(item), rep)
        except Exception:  # never break the run over the report
            self.error = traceback.format_exc()
        return rep

    def _update(self, record: Scenario, rep) -> None:
        record.duration_s += float(getattr(rep, "duration", 0.0) or 0.0)
        when = rep.when
        if hasattr(rep, "wasxfail"):
            if rep.skipped:
                record.outcome = "skipped"
                record.message = f"xfail: {rep.wasxfail}".rstrip(": ")
            elif rep.passed and when == "call":
                record.outcome = "passed"
                record.message = f"xpass: {rep.wasxfail}".rstrip(": ")
            return
        if rep.skipped:
            record.outcome = "skipped"
            longrepr = rep.longrepr
            if isinstance(longrepr, tuple) and len(longrepr) == 3:
                record.message = str(longrepr[2])
            return
        if rep.failed:
            if when == "call":
                record.outcome = "failed"
            elif when == "setup" or record.outcome in (None, "passed", "skipped"):
                record.outcome = "error"
            crash = getattr(getattr(rep, "longrepr", None), "reprcrash", None)
            message = getattr(crash, "message", None) or (rep.longreprtext.strip().splitlines() or [""])[-1]
            prefix = "" if when == "call" else f"in {when}: "
            record.message = (record.message + "\n" if record.message and when == "teardown" else "") + prefix + message
            text = rep.longreprtext
            if len(text) > LONGREPR_LIMIT:
                text = text[:LONGREPR_LIMIT // 2] + "\n[... cut ...]\n" + text[-LONGREPR_LIMIT // 2:]
            record.longrepr = (record.longrepr + "\n\n" if record.longrepr else "") + text
            return
        if when == "call":
            record.outcome = "passed"
        elif when == "setup" and record.outcome is None:
            pass  # the call phase decides
        elif when == "teardown" and record.outcome is None:
            record.outcome = "passed"

    def pytest_collectreport(self, report):
        """A scenario file that fails to import is a scenario that errored."""
        if not report.failed:
            return
        try:
            path = Path(self.config.rootpath) / report.nodeid.split("::", 1)[0]
            if not (report.nodeid and _under_scenarios(path, Path(self.config.rootpath))):
                return
            record = self.records.setdefault(report.nodeid, Scenario(
                nodeid=report.nodeid, name=report.nodeid.rsplit("/", 1)[-1], started=_iso(time.time())))
            record.outcome = "error"
            text = report.longreprtext
            record.message = "collection failed: " + ((text.strip().splitlines() or [""])[-1])
            record.longrepr = text[:LONGREPR_LIMIT]
        except Exception:
            self.error = traceback.format_exc()

    # -- the end ---------------------------------------------------------
    @pytest.hookimpl(trylast=True)
    def pytest_sessionfinish(self, session, exitstatus):
        finished = time.time()
        if not self.records:
            self._drop_unused_junit()
            return
        try:
            self.written = self.write(int(exitstatus), finished)
        except Exception:
            self.error = traceback.format_exc()

    def _drop_unused_junit(self) -> None:
        """pytest wrote junit.xml into a report directory that got no report:
        remove it (and the directory, if that leaves it empty)."""
        if self.junit_mode != "pytest" or self.explicit_dir:
            return
        try:
            (self.run_dir / JUNIT_XML).unlink(missing_ok=True)
            self.run_dir.rmdir()
        except OSError:
            pass

    def run_info(self, exitstatus: int | None, finished: float) -> RunInfo:
        config = self.config
        deep_opt = config.getoption("--deep", default=None)
        container_exe = config.getoption("--container-exe", default=None)
        return RunInfo(
            id=self.run_id,
            label=config.getoption("--run-label", default=None),
            started=_iso(self.started),
            finished=_iso(finished),
            duration_s=round(finished - self.started, 3),
            exit_status=exitstatus,
            pytest_args=[str(a) for a in config.invocation_params.args],
            python=env.python_version(),
            host=env.host_info(),
            git=env.git_info(repo_root()),
            container_exe=None if container_exe is None else str(container_exe),
            deep=bool(deep_opt) or os.environ.get(ENV_DEEP, "") == "1",
        )

    def write(self, exitstatus: int | None, finished: float) -> Path:
        run_dir = self.run_dir
        run_dir.mkdir(parents=True, exist_ok=True)
        run = self.run_info(exitstatus, finished)
        report = Report(run=run, scenarios=list(self.records.values()))
        junit = run_dir / JUNIT_XML
        if self.junit_mode == "pytest":
            run.junit_writer = "pytest"
        elif self.junit_mode == "user" and self.user_junit is not None and self.user_junit.is_file():
            if self.user_junit.resolve() != junit.resolve():
                shutil.copyfile(self.user_junit, junit)
            run.junit_writer = f"pytest (--junitxml {self.user_junit}, copied)"
        else:
            write_junit(report.scenarios, junit)
            run.junit_writer = "cloneguard"
        run.junit = JUNIT_XML
        report.save_json(run_dir)
        write_html(report, run_dir / REPORT_HTML)
        if run_dir.parent.resolve() == self.reports_root.resolve():
            update_latest(self.reports_root, run_dir.name)
        return run_dir

    def pytest_terminal_summary(self, terminalreporter):
        tr = terminalreporter
        if self.error:
            tr.write_sep("-", "cloneguard report: internal error", red=True)
            tr.write_line(self.error.rstrip())
        if self.written is None:
            return
        records = list(self.records.values())
        counts = {k: 0 for k in TRIAL_OUTCOMES}
        unmet = 0
        for r in records:
            for k, v in r.counts().items():
                counts[k] = counts.get(k, 0) + v
            unmet += sum(1 for x in r.expectations if not x.met)
        total = sum(counts.values())
        detail = ", ".join(f"{v} {k}" for k, v in counts.items() if v) or "no trials"
        tr.write_sep("-", "cloneguard resilience report")
        tr.write_line(f"{len(records)} scenario(s), {total} trial(s): {detail}"
                      + (f"; {unmet} expectation(s) not met" if unmet else ""))
        tr.write_line(f"report: {self.written / REPORT_HTML}")
        tr.write_line(f"data:   {self.written / 'report.json'}")


def update_latest(root: Path, run_name: str) -> Path:
    """Point ``root/latest`` at ``run_name``: a relative symlink, replaced
    atomically, or a text file holding the name where symlinks fail."""
    link = root / LATEST
    tmp = root / f".{LATEST}.{os.getpid()}.{secrets.token_hex(2)}"
    try:
        os.symlink(run_name, tmp)
        os.replace(tmp, link)
    except OSError:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        if link.is_symlink():
            link.unlink()
        write_atomic(link, run_name + "\n")
    return link


def _classname(nodeid: str) -> tuple[str, str]:
    parts = nodeid.split("::")
    module = parts[0]
    if module.endswith(".py"):
        module = module[:-3]
    module = module.replace("/", ".").replace("\\", ".")
    return ".".join([module] + parts[1:-1]), parts[-1] if len(parts) > 1 else parts[0]


def write_junit(scenarios: list[Scenario], path: Path) -> Path:
    """A JUnit XML of the scenarios, for sessions where pytest's own writer
    was not pointed at the report directory."""
    suite = ET.Element("testsuite", name="cloneguard-scenarios")
    counts = {"failures": 0, "errors": 0, "skipped": 0}
    total_time = 0.0
    for s in scenarios:
        classname, name = _classname(s.nodeid)
        case = ET.SubElement(suite, "testcase", classname=classname, name=name, time=f"{s.duration_s:.3f}")
        total_time += s.duration_s
        if s.outcome == "failed":
            counts["failures"] += 1
            ET.SubElement(case, "failure", message=s.message or "failed").text = s.longrepr or ""
        elif s.outcome in ("error", None):
            counts["errors"] += 1
            ET.SubElement(case, "error", message=s.message or "error").text = s.longrepr or ""
        elif s.outcome == "skipped":
            counts["skipped"] += 1
            ET.SubElement(case, "skipped", message=s.message or "skipped")
    suite.set("tests", str(len(scenarios)))
    for k, v in counts.items():
        suite.set(k, str(v))
    suite.set("time", f"{total_time:.3f}")
    suites = ET.Element("testsuites")
    suites.append(suite)
    ET.indent(suites)
    write_atomic(path, ET.tostring(suites, encoding="unicode", xml_declaration=True) + "\n")
    return path


# --------------------------------------------------------------------------
# Module-level hooks and the fixture
# --------------------------------------------------------------------------
def pytest_addoption(parser):
    group = parser.getgroup("cloneguard-report", "cloneguard crash-resilience reports")
    group.addoption(
        "--report-dir", default=None, metavar="PATH",
        help=f"directory for this run's report.json, report.html and junit.xml "
             f"(env {ENV_REPORT_DIR}; default: <repo>/reports/<UTC time>-<random>)",
    )
    group.addoption("--run-label", default=None, metavar="TEXT", help="a label for this run, shown in the report")


@pytest.hookimpl(tryfirst=True)
def pytest_configure(config):
    # Before pytest's junitxml plugin reads --junitxml. Not on xdist workers.
    if hasattr(config, "workerinput"):
        return
    session = ReportSession(config)
    config.stash[_SESSION] = session
    session.configure_junit()
    config.pluginmanager.register(session, "cloneguard-report-session")


def pytest_unconfigure(config):
    session = config.stash.get(_SESSION, None)
    if session is not None:
        config.pluginmanager.unregister(session)
        del config.stash[_SESSION]


@pytest.fixture
def resilience(request) -> Resilience:
    """Records a scenario's description, trials, hangs, expectations and notes
    for the crash-resilience report."""
    session = request.config.stash.get(_SESSION, None)
    if session is None:  # e.g. an xdist worker: record, but nowhere to report
        scenario = Scenario(nodeid=request.node.nodeid, name=request.node.name, used_resilience=True)
        return Resilience(scenario)
    return session.recorder_for(request.node)
