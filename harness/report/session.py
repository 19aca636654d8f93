"""The report session: one per pytest run, in the process that writes the
report (the one pytest process, or the xdist controller). It takes every
test's reports (its own, or an xdist worker's), keeps one Scenario per test,
and at the end writes ``report.json``, ``report.html`` and ``junit.xml`` into
the run's report directory and points ``reports/latest`` at it.

The plugin (collect.py) makes it and registers it as a plugin of its own.
"""

from __future__ import annotations

import os
import shutil
import time
import traceback
from datetime import UTC, datetime
from pathlib import Path

import pytest

from .. import plan
from ..plan import trial_plan_of
from . import env, paths
from .junit import write_junit
from .model import JUNIT_XML, REPORT_HTML, TRIAL_OUTCOMES, Report, RunInfo, Scenario
from .record import RECORD_ATTR, _iso
from .render import write_html

#: The ini option naming the directories whose tests are scenarios (a
#: report each run), and its default.
SCENARIO_DIRS_INI = "cloneguard_scenario_dirs"
SCENARIO_DIRS = ["scenarios"]
#: longest pytest failure text kept per test
LONGREPR_LIMIT = 40_000


def scenario_dirs(config: pytest.Config) -> list[str]:
    """The directory names (or paths from the root directory) whose tests
    get a report."""
    return [d.strip("/") for d in config.getini(SCENARIO_DIRS_INI) or SCENARIO_DIRS]


def _under_scenarios(path: Path, root: Path, dirs: list[str]) -> bool:
    """Whether ``path`` (a test file, or a directory) is inside a scenario
    directory: one named as a ``dirs`` entry, or an entry's path from
    ``root``."""
    try:
        parts = path.resolve().relative_to(root.resolve()).parts
    except ValueError:
        parts = path.resolve().parts
    folders = parts[:-1] if path.suffix else parts
    for d in dirs:
        wanted = tuple(Path(d).parts)
        if len(wanted) == 1 and wanted[0] in folders:
            return True
        if len(wanted) > 1 and folders[: len(wanted)] == wanted:
            return True
    return False


def _args_run_scenarios(config: pytest.Config) -> bool:
    """Whether the command line names a scenario directory, a file in one,
    or a directory holding one."""
    base = Path(config.invocation_params.dir)
    root = Path(config.rootpath)
    dirs = scenario_dirs(config)
    for arg in config.args:
        text = str(arg).split("::", 1)[0]
        if not text or text.startswith("-"):
            continue
        path = base / text
        if _under_scenarios(path, root, dirs):
            return True
        if path.is_dir() and any((path / d).is_dir() for d in dirs):
            return True
    return False


class ReportSession:
    """Collects one Scenario per test from the test reports (its own, or an
    xdist worker's) and writes the report at the end. Lives only in the
    process that writes the report: the one pytest process, or the xdist
    controller."""

    def __init__(self, config: pytest.Config):
        self.config = config
        self.started = time.time()
        self.records: dict[str, Scenario] = {}  # every test seen, in order
        self.in_scope: set[str] = set()  # ... that go in the report
        self.workers: set[str] = set()
        self.reports_root = paths.default_reports_root(config.rootpath)
        option_dir = config.getoption("--report-dir", default=None)
        chosen = option_dir or os.environ.get(paths.ENV_REPORT_DIR) or None
        if chosen:
            path = Path(os.path.expanduser(chosen))
            if not path.is_absolute():
                path = Path(config.invocation_params.dir) / path
            self.run_dir = path
            self.run_id = path.name
        else:
            self.run_id = paths.new_run_id(datetime.fromtimestamp(self.started, UTC))
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
    def _record(self, nodeid: str) -> Scenario:
        record = self.records.get(nodeid)
        if record is None:
            name = nodeid.rsplit("::", 1)[-1]
            record = Scenario(nodeid=nodeid, name=name, started=_iso(time.time()))
            self.records[nodeid] = record
        return record

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        """Every phase report of every test, from this process or a worker."""
        try:
            record = self._record(report.nodeid)
            path = Path(self.config.rootpath) / report.nodeid.split("::", 1)[0]
            if _under_scenarios(path, Path(self.config.rootpath), scenario_dirs(self.config)):
                self.in_scope.add(report.nodeid)
            worker = getattr(getattr(getattr(report, "node", None), "gateway", None), "id", None)
            if worker:
                self.workers.add(worker)
            self._update(record, report)
            data = getattr(report, RECORD_ATTR, None)
            if data is not None:
                self.in_scope.add(report.nodeid)
                _take_recorded(record, Scenario.from_dict(data))
        except Exception:  # never break the run over the report
            self.error = traceback.format_exc()

    def _update(self, record: Scenario, rep: pytest.TestReport) -> None:
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
                text = text[: LONGREPR_LIMIT // 2] + "\n[... cut ...]\n" + text[-LONGREPR_LIMIT // 2 :]
            record.longrepr = (record.longrepr + "\n\n" if record.longrepr else "") + text
            return
        if when == "call":
            record.outcome = "passed"
        elif when == "setup" and record.outcome is None:
            pass  # the call phase decides
        elif when == "teardown" and record.outcome is None:
            record.outcome = "passed"

    def pytest_collectreport(self, report: pytest.CollectReport) -> None:
        """A scenario file that fails to import is a scenario that errored."""
        if not report.failed:
            return
        try:
            path = Path(self.config.rootpath) / report.nodeid.split("::", 1)[0]
            if not (report.nodeid and _under_scenarios(path, Path(self.config.rootpath), scenario_dirs(self.config))):
                return
            record = self.records.setdefault(
                report.nodeid,
                Scenario(nodeid=report.nodeid, name=report.nodeid.rsplit("/", 1)[-1], started=_iso(time.time())),
            )
            self.in_scope.add(report.nodeid)
            record.outcome = "error"
            text = report.longreprtext
            record.message = "collection failed: " + ((text.strip().splitlines() or [""])[-1])
            record.longrepr = text[:LONGREPR_LIMIT]
        except Exception:
            self.error = traceback.format_exc()

    # -- the end ---------------------------------------------------------
    @pytest.hookimpl(trylast=True)
    def pytest_sessionfinish(self, session: pytest.Session, exitstatus: int | pytest.ExitCode) -> None:
        finished = time.time()
        if not self.in_scope:
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
            git=env.git_info(Path(config.rootpath)),
            project=env.project_name(Path(config.invocation_params.dir), Path(config.rootpath)),
            packages=env.package_versions(),
            container_exe=None if container_exe is None else str(container_exe),
            deep=plan.is_deep(config),
            workers=len(self.workers),
            plan=trial_plan_of(config),
            shard=config.getoption("--shard", default=None),
        )

    def write(self, exitstatus: int | None, finished: float) -> Path:
        run_dir = self.run_dir
        run_dir.mkdir(parents=True, exist_ok=True)
        run = self.run_info(exitstatus, finished)
        report = Report(run=run, scenarios=[r for n, r in self.records.items() if n in self.in_scope])
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
            paths.update_latest(self.reports_root, run_dir.name)
        return run_dir

    def pytest_terminal_summary(self, terminalreporter: pytest.TerminalReporter) -> None:
        tr = terminalreporter
        if self.error:
            tr.write_sep("-", "cloneguard report: internal error", red=True)
            tr.write_line(self.error.rstrip())
        if self.written is None:
            return
        records = [r for n, r in self.records.items() if n in self.in_scope]
        counts = {k: 0 for k in TRIAL_OUTCOMES}
        unmet = 0
        for r in records:
            for k, v in r.counts().items():
                counts[k] = counts.get(k, 0) + v
            unmet += sum(1 for x in r.expectations if x.met is False)
        total = sum(counts.values())
        detail = ", ".join(f"{v} {k}" for k, v in counts.items() if v) or "no trials"
        tr.write_sep("-", "cloneguard resilience report")
        where = f" on {len(self.workers)} workers" if self.workers else ""
        shard = self.config.getoption("--shard", default=None)
        tr.write_line(
            f"{len(records)} scenario(s), {total} trial(s){where}: {detail}"
            + (f"; {unmet} expectation(s) not met" if unmet else "")
            + (f"; shard {shard}: expectations are judged by `python -m cloneguard.harness merge`" if shard else "")
        )
        tr.write_line(f"report: {self.written / REPORT_HTML}")
        tr.write_line(f"data:   {self.written / 'report.json'}")


def _take_recorded(record: Scenario, recorded: Scenario) -> None:
    """What the test recorded through ``resilience`` goes into the session's
    record of it (which keeps pytest's verdict, duration and failure text)."""
    for name in ("fault", "profile", "claim"):
        if getattr(recorded, name) is not None:
            setattr(record, name, getattr(recorded, name))
    if recorded.name != record.name:
        record.name = recorded.name
    record.mitigations, record.units = recorded.mitigations, recorded.units
    record.used_resilience = True
    record.started = recorded.started or record.started
    record.trials, record.hangs = recorded.trials, recorded.hangs
    record.expectations, record.notes = recorded.expectations, recorded.notes
