"""Crash-resilience reports: statistics, the pytest plugin end to end (in
pytester sessions), report.html, compare and render."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import textwrap
import xml.etree.ElementTree as ET
from importlib.metadata import entry_points
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cloneguard.harness.__main__ import main as harness_main
from cloneguard.harness.plan import ENV_DEEP
from cloneguard.harness.report import charts, paths, stats
from cloneguard.harness.report.compare import compare_reports, format_comparison, match_scenarios
from cloneguard.harness.report.model import (
    Hang,
    Report,
    RunInfo,
    Scenario,
    Trial,
    load_report,
    resolve_report_path,
)
from cloneguard.harness.report.render import render_html, scenario_status

pytest_plugins = ["pytester"]

REPO = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------
# statistics
# --------------------------------------------------------------------------
# Hand-computed with z = 1.959964 (z² = 3.841459):
#   0/10:  upper = (z²/n) / (1 + z²/n) = 0.384146 / 1.384146 = 0.277533
#   10/10: lower = 1 - 0.277533 = 0.722467 (the interval is symmetric in k <-> n-k)
#   5/10:  centre 0.5, half = z/(1 + z²/n) * sqrt(0.25/10 + z²/400)
#          = 1.416009 * sqrt(0.034604) = 0.263407
#   95/100: centre = (0.95 + 0.019207) / 1.038415 = 0.933353,
#          half = 1.887458 * sqrt(0.000475 + 0.0000960365) = 0.045104
@pytest.mark.parametrize(
    "k, n, low, high",
    [
        (0, 10, 0.0, 0.277533),
        (10, 10, 0.722467, 1.0),
        (5, 10, 0.236593, 0.763407),
        (95, 100, 0.888249, 0.978457),
    ],
)
def test_wilson_interval_hand_computed(k, n, low, high):
    got_low, got_high = stats.wilson_interval(k, n)
    assert got_low == pytest.approx(low, abs=2e-6)
    assert got_high == pytest.approx(high, abs=2e-6)


def test_wilson_interval_edges():
    assert stats.wilson_interval(0, 0) == (0.0, 1.0)
    with pytest.raises(ValueError):
        stats.wilson_interval(3, 2)
    with pytest.raises(ValueError):
        stats.wilson_interval(-1, 2)
    # a higher confidence gives a wider interval
    lo95, hi95 = stats.wilson_interval(7, 10, 0.95)
    lo99, hi99 = stats.wilson_interval(7, 10, 0.99)
    assert lo99 < lo95 < 0.7 < hi95 < hi99


@given(
    st.integers(min_value=1, max_value=2000).flatmap(
        lambda n: st.tuples(st.integers(min_value=0, max_value=n), st.just(n))
    )
)
def test_wilson_interval_properties(kn):
    k, n = kn
    low, high = stats.wilson_interval(k, n)
    assert 0.0 <= low <= k / n <= high <= 1.0
    mirror_low, mirror_high = stats.wilson_interval(n - k, n)
    assert low == pytest.approx(1.0 - mirror_high, abs=1e-12)
    assert high == pytest.approx(1.0 - mirror_low, abs=1e-12)


def test_two_proportion_z_test_hand_computed():
    # 18/20 vs 10/20: pooled 0.7, se = sqrt(0.7*0.3*(1/20+1/20)) = 0.144914,
    # z = 0.4 / 0.144914 = 2.760262, two-sided p = erfc(z/sqrt 2) = 0.005775
    z, p = stats.two_proportion_z_test(18, 20, 10, 20)
    assert z == pytest.approx(2.760262, abs=1e-5)
    assert p == pytest.approx(0.005775, abs=2e-5)
    assert stats.two_proportion_z_test(20, 20, 30, 30) == (0.0, 1.0)
    with pytest.raises(ValueError):
        stats.two_proportion_z_test(0, 0, 1, 2)


def test_quantiles_and_latency_summary():
    assert stats.quantile([1.0, 2.0, 3.0, 4.0], 0.5) == 2.5
    assert stats.quantile([1.0, 2.0, 3.0, 4.0], 0.9) == pytest.approx(3.7)
    summary = stats.summarize(float(v) for v in range(100, 0, -1))  # unsorted input
    assert summary is not None
    assert (summary.n, summary.min, summary.max) == (100, 1.0, 100.0)
    assert summary.median == 50.5
    assert summary.p90 == pytest.approx(90.1)
    assert summary.p99 == pytest.approx(99.01)
    assert summary.mean == 50.5
    assert stats.summarize([]) is None


# --------------------------------------------------------------------------
# the pytest plugin, in pytester sessions
# --------------------------------------------------------------------------
def plugin_args() -> list[str]:
    """Load harness.report.collect into a pytester session: by its pytest11
    entry point's name when one is installed (so autoloading does not
    register the module a second time), else by module name."""
    for ep in entry_points(group="pytest11"):
        if ep.value == "cloneguard.harness.report.collect":
            return ["-p", ep.name]
    return ["-p", "cloneguard.harness.report.collect"]


STACKS = 'Thread 1 "<main>":\n  #0 futex_wait (lock=0x7f00) at futex.c:12\n  #1 if (a && b > c) <lock>'

SCENARIO = f"""
import pytest

STACKS = {STACKS!r}


@pytest.mark.parametrize("profile", ["per-node", "shared"])
def test_segfault(resilience, profile):
    resilience.describe(fault="segfault-gil-held", profile=profile, mitigations={{"gil_repair": True}},
                        claim="the container survives a SIGSEGV in one node's callback")
    outcomes = ["survived"] * 9 + ["hung"] if profile == "per-node" else ["survived"] * 4 + ["crashed"] * 6
    for i, outcome in enumerate(outcomes):
        index = resilience.trial(outcome=outcome, seed=100 + i,
                                 latency_ms={{"death_to_event": 0.25 * (i + 1), "load_to_loaded": [10.0, 20.0]}},
                                 details={{"victim": "/victim"}})
        assert index == i
    if profile == "per-node":
        resilience.hang(trial=9, summary="parent blocked on futex owned by dead tid 1234 (node /victim)",
                        stacks=STACKS, lock=0x7F0012345678, owner_tid=1234, owner_node="/victim")
    resilience.note("checked with <valgrind> & friends")
    resilience.expect_rate("survived", at_least=0.8)


def test_abort(resilience):
    resilience.describe(fault="abort", profile="per-node", claim="an abort stays in its node")
    for i in range(3):
        resilience.trial("survived", seed=i)


def test_plain():
    pass
"""


def run_session(pytester, *args, files=None):
    scenarios = pytester.mkdir("scenarios")
    for name, text in (files or {"test_fake.py": SCENARIO}).items():
        (scenarios / name).write_text(textwrap.dedent(text))
    return pytester.runpytest(*plugin_args(), *args)


@pytest.fixture
def report_root(tmp_path, monkeypatch):
    """The plugin's default reports root, moved into tmp_path, and no
    report directory named through the environment."""
    root = tmp_path / "reports-root"
    monkeypatch.setattr(paths, "default_reports_root", lambda rootdir: root)
    monkeypatch.delenv(paths.ENV_REPORT_DIR, raising=False)
    return root


def _check_per_node_cell(per_node: dict) -> None:
    """The per-node segfault cell of the session's report.json: its trials,
    statistics, hang and expectation."""
    assert per_node["fault"] == "segfault-gil-held" and per_node["profile"] == "per-node"
    assert per_node["mitigations"] == {"gil_repair": True}
    assert per_node["outcome"] == "passed"
    assert per_node["used_resilience"] is True
    assert len(per_node["trials"]) == 10
    assert per_node["trials"][3] == {
        "index": 3,
        "outcome": "survived",
        "seed": 103,
        "latency_ms": {"death_to_event": 1.0, "load_to_loaded": [10.0, 20.0]},
        "details": {"victim": "/victim"},
        "time": per_node["trials"][3]["time"],
    }
    assert per_node["stats"]["counts"] == {"survived": 9, "hung": 1, "crashed": 0, "failed": 0, "corrupted": 0}
    survival = per_node["stats"]["survival"]
    assert (survival["successes"], survival["trials"]) == (9, 10)
    assert (survival["low"], survival["high"]) == pytest.approx(stats.wilson_interval(9, 10))
    lat = per_node["stats"]["latency_ms"]
    assert lat["death_to_event"]["n"] == 10 and lat["death_to_event"]["median"] == pytest.approx(1.375)
    assert lat["load_to_loaded"]["n"] == 20 and lat["load_to_loaded"]["max"] == 20.0
    (hang,) = per_node["hangs"]
    assert hang["trial"] == 9 and hang["lock"] == "0x7f0012345678"
    assert hang["owner_tid"] == 1234 and hang["owner_node"] == "/victim" and hang["stacks"] == STACKS
    assert per_node["expectations"] == [
        {
            "outcome": "survived",
            "at_least": 0.8,
            "at_most": None,
            "successes": 9,
            "trials": 10,
            "rate": 0.9,
            "ci_low": survival["low"],
            "ci_high": survival["high"],
            "met": True,
        }
    ]
    assert per_node["notes"] == ["checked with <valgrind> & friends"]


def test_session_writes_report_json_html_and_junit(pytester, tmp_path, report_root):
    out = tmp_path / "run-1"
    result = run_session(
        pytester,
        "--report-dir",
        str(out),
        "--run-label",
        "smoke <1>",
        "--container-exe",
        "/opt/fake/component_container",
        "scenarios",
    )
    result.assert_outcomes(passed=3, failed=1)
    result.stdout.fnmatch_lines(["*cloneguard resilience report*", f"report: {out / 'report.html'}"])

    data = json.loads((out / "report.json").read_text())
    run = data["run"]
    assert run["id"] == "run-1"
    assert run["label"] == "smoke <1>"
    assert run["container_exe"] == "/opt/fake/component_container"
    assert run["exit_status"] == 1
    assert "--report-dir" in run["pytest_args"]
    assert run["host"]["kernel"] == os.uname().release
    assert run["host"]["glibc"] == os.confstr("CS_GNU_LIBC_VERSION")
    assert isinstance(run["host"]["pku"], bool)
    assert run["junit"] == "junit.xml" and run["junit_writer"] == "pytest"

    by_id = {s["nodeid"]: s for s in data["scenarios"]}
    assert set(by_id) == {
        "scenarios/test_fake.py::test_segfault[per-node]",
        "scenarios/test_fake.py::test_segfault[shared]",
        "scenarios/test_fake.py::test_abort",
        "scenarios/test_fake.py::test_plain",  # under scenarios/, no fixture: still recorded
    }
    _check_per_node_cell(by_id["scenarios/test_fake.py::test_segfault[per-node]"])

    shared = by_id["scenarios/test_fake.py::test_segfault[shared]"]
    assert shared["outcome"] == "failed"
    assert shared["expectations"][0]["met"] is False
    assert "4/10" in shared["message"] and "survived" in shared["message"]
    assert by_id["scenarios/test_fake.py::test_plain"]["used_resilience"] is False
    assert data["summary"]["outcomes"] == {"passed": 3, "failed": 1, "skipped": 0, "error": 0}
    assert data["summary"]["trials"] == 23 and data["summary"]["hangs"] == 1

    html = (out / "report.html").read_text()
    assert "9/10 survived" in html and "4/10 survived" in html  # the matrix cells
    assert "expect survived ≥ 80.0% ✓" in html and "expect survived ≥ 80.0% ✗" in html
    assert "futex_wait" in html
    assert "if (a &amp;&amp; b &gt; c) &lt;lock&gt;" in html and "&quot;&lt;main&gt;&quot;" in html
    assert "<main>" not in html and "<lock>" not in html and "<valgrind>" not in html
    assert "smoke &lt;1&gt;" in html
    assert "<script" not in html and "http://" not in html.replace('xmlns="http://www.w3.org/2000/svg"', "")

    suite = ET.parse(out / "junit.xml").getroot()
    cases = suite.findall(".//testcase")
    assert len(cases) == 4
    assert len(suite.findall(".//failure")) == 1


def test_default_directory_is_the_projects_own_and_latest_link(pytester, monkeypatch):
    # reports/ under the run's root directory: the project under test's,
    # not this harness's checkout.
    monkeypatch.delenv(paths.ENV_REPORT_DIR, raising=False)
    report_root = pytester.path / "reports"
    first = run_session(pytester, "scenarios")
    first.assert_outcomes(passed=3, failed=1)
    runs = sorted(p for p in report_root.iterdir() if p.name != "latest")
    assert len(runs) == 1
    run_dir = runs[0]
    assert paths.new_run_id().split("T")[0].isdigit()
    assert len(run_dir.name) == len("20261122T031500Z-a1b2") and run_dir.name[8] == "T"
    assert (run_dir / "junit.xml").is_file()  # pytest's writer, redirected before it configured
    assert json.loads((run_dir / "report.json").read_text())["run"]["junit_writer"] == "pytest"
    latest = report_root / "latest"
    assert latest.is_symlink() and latest.resolve() == run_dir.resolve()
    assert resolve_report_path(latest) == (run_dir / "report.json").resolve()


def test_no_report_without_scenarios(pytester, report_root):
    pytester.makepyfile(test_unit="def test_one():\n    pass\n")
    result = pytester.runpytest(*plugin_args())
    result.assert_outcomes(passed=1)
    assert not report_root.exists()
    assert "cloneguard resilience report" not in result.stdout.str()


@pytest.mark.parametrize("dirs", ["hil_tests", "robot/hil_tests"])
def test_a_projects_own_test_folder_is_named_a_scenario_folder_in_its_ini(pytester, report_root, dirs):
    pytester.makeini(f"[pytest]\ncloneguard_scenario_dirs = {dirs}\n")
    folder = pytester.mkpydir("robot") / "hil_tests"
    folder.mkdir()
    (folder / "test_robot.py").write_text("def test_planner_outlives():\n    pass\n")
    pytester.makepyfile(test_unit="def test_one():\n    pass\n")
    result = pytester.runpytest(*plugin_args())
    result.assert_outcomes(passed=2)
    (run_dir,) = [p for p in report_root.iterdir() if p.name != "latest"]
    names = [s["name"] for s in json.loads((run_dir / "report.json").read_text())["scenarios"]]
    assert names == ["test_planner_outlives"]  # that folder's tests only
    assert (run_dir / "junit.xml").is_file()


def test_resilience_outside_scenarios_still_reports(pytester, report_root):
    """Nothing on the command line said "scenarios", so pytest's JUnit writer
    was not redirected: the plugin writes junit.xml itself."""
    pytester.makepyfile(
        test_odd=textwrap.dedent("""
        def test_uses_fixture(resilience):
            resilience.describe(fault="kill", profile="thread")
            resilience.trial("crashed")
            resilience.expect_rate("crashed", at_least=1.0)

        def test_fails(resilience):
            resilience.trial("survived")
            assert False, "boom <here>"
    """)
    )
    result = pytester.runpytest(*plugin_args())
    result.assert_outcomes(passed=1, failed=1)
    (run_dir,) = [p for p in report_root.iterdir() if p.name != "latest"]
    data = json.loads((run_dir / "report.json").read_text())
    assert data["run"]["junit_writer"] == "cloneguard"
    suite = ET.parse(run_dir / "junit.xml").getroot()
    assert [c.get("name") for c in suite.iter("testcase")] == ["test_uses_fixture", "test_fails"]
    (failure,) = suite.iter("failure")
    message = failure.get("message")
    assert message is not None and "boom <here>" in message


def test_report_dir_from_environment_and_user_junit(pytester, tmp_path, report_root, monkeypatch):
    out = tmp_path / "from-env"
    monkeypatch.setenv(paths.ENV_REPORT_DIR, str(out))
    user_xml = tmp_path / "mine.xml"
    result = run_session(pytester, f"--junitxml={user_xml}", "scenarios")
    result.assert_outcomes(passed=3, failed=1)
    assert user_xml.is_file()
    assert (out / "junit.xml").read_bytes() == user_xml.read_bytes()
    data = json.loads((out / "report.json").read_text())
    assert data["run"]["id"] == "from-env"
    assert "copied" in data["run"]["junit_writer"]
    assert not report_root.exists()  # no "latest" outside the default root


def test_deep_mode_and_broken_scenario_file(pytester, tmp_path, report_root, monkeypatch):
    monkeypatch.setenv(ENV_DEEP, "1")
    out = tmp_path / "run"
    result = run_session(
        pytester,
        "--report-dir",
        str(out),
        "--continue-on-collection-errors",
        "scenarios",
        files={
            "test_ok.py": "def test_ok(resilience):\n    resilience.trial('survived')\n",
            "test_broken.py": "import no_such_module_here\n",
        },
    )
    assert result.ret != 0
    data = json.loads((out / "report.json").read_text())
    assert data["run"]["deep"] is True
    by_id = {s["nodeid"]: s for s in data["scenarios"]}
    assert by_id["scenarios/test_ok.py::test_ok"]["outcome"] == "passed"
    broken = by_id["scenarios/test_broken.py"]
    assert broken["outcome"] == "error" and "no_such_module_here" in broken["longrepr"]
    html = (out / "report.html").read_text()
    assert "collection failed" in html


def test_fixture_rejects_bad_input(pytester, tmp_path, report_root):
    out = tmp_path / "run"
    result = run_session(
        pytester,
        "--report-dir",
        str(out),
        "scenarios",
        files={
            "test_bad.py": """
        import math
        import pytest

        def test_bad(resilience):
            with pytest.raises(ValueError):
                resilience.trial("exploded")
            with pytest.raises(ValueError):
                resilience.trial("survived", latency_ms={"x": math.nan})
            with pytest.raises(TypeError):
                resilience.trial("survived", latency_ms={"x": "fast"})
            with pytest.raises(ValueError):
                resilience.expect_rate("survived")
            with pytest.raises(AssertionError, match="no trials"):
                resilience.expect_rate("survived", at_least=0.5)
            resilience.trial("survived", latency_ms={"x": None, "y": 2})
            resilience.trial("hung", seed=41, details={"why": "no /odom within 10.0 s"})
            assert resilience.counts()["hung"] == 1
            assert resilience.rate("survived").rate == 0.5
            resilience.expect_rate("hung", at_most=0.5)
            # the failure names the trials against it, and why: a CI log shows only this line
            with pytest.raises(AssertionError, match=r"1/2 trials hung.*; trial 1 \\(seed 41\\) hung: no /odom within"):
                resilience.expect_rate("hung", at_most=0.25)
            with pytest.raises(AssertionError, match=r"1/2 trials survived.*; trial 1 \\(seed 41\\) hung: no /odom"):
                resilience.expect_rate("survived", at_least=0.99)
            resilience.hang(trial=1, summary="no lock found", lock="")
    """
        },
    )
    result.assert_outcomes(passed=1)
    (scenario,) = json.loads((out / "report.json").read_text())["scenarios"]
    assert [t["latency_ms"] for t in scenario["trials"]] == [{"y": 2.0}, {}]
    assert [e["met"] for e in scenario["expectations"]] == [False, True, False, False]
    assert scenario["hangs"][0]["lock"] is None


def test_update_latest_falls_back_to_a_text_file(tmp_path, monkeypatch):
    (tmp_path / "run-a").mkdir()
    (tmp_path / "run-b").mkdir()
    Report(RunInfo(id="run-b")).save_json(tmp_path / "run-b")
    paths.update_latest(tmp_path, "run-a")
    paths.update_latest(tmp_path, "run-b")
    assert os.readlink(tmp_path / "latest") == "run-b"

    def no_symlinks(*args, **kwargs):
        raise OSError("symlinks not supported here")

    monkeypatch.setattr(os, "symlink", no_symlinks)
    paths.update_latest(tmp_path, "run-b")
    latest = tmp_path / "latest"
    assert not latest.is_symlink() and latest.read_text().strip() == "run-b"
    assert load_report(latest).run.id == "run-b"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".latest")]


# --------------------------------------------------------------------------
# report.html details
# --------------------------------------------------------------------------
def make_scenario(nodeid, survived, total, *, fault="segv", profile="per-node", latency=None, **kw) -> Scenario:
    trials = []
    for i in range(total):
        lat = {"death_to_event": latency(i)} if latency else {}
        trials.append(Trial(index=i, outcome="survived" if i < survived else "crashed", seed=i, latency_ms=lat))
    return Scenario(
        nodeid=nodeid, name=nodeid.split("::")[-1], fault=fault, profile=profile, outcome="passed", trials=trials, **kw
    )


def test_html_escapes_everything_and_colours_cells():
    evil = Scenario(
        nodeid="scenarios/x.py::test_<evil>",
        name="test_<evil>",
        fault="<img src=x>",
        profile='"quoted"',
        claim="survives </section><script>alert(1)</script>",
        outcome="failed",
        message="assert 1 < 2 & 3 > 4",
        longrepr="E   <trace>",
        hangs=[Hang(summary="blocked <on> lock", stacks="<frame>", lock="0x1", details={"k": "<v>"})],
        notes=["<note>"],
        mitigations={"<m>": "<x>"},
    )
    report = Report(
        RunInfo(id="r<1>", label="<label>", git={"commit": "abc", "branch": "<br>"}),
        [
            evil,
            make_scenario("s.py::test_ok", 10, 10),
            make_scenario("s.py::test_meh", 9, 10, profile="shared"),
            make_scenario("s.py::test_bad", 2, 10, profile="third"),
        ],
    )
    html = render_html(report)
    for raw in ("<script", "<img", "<evil>", "<frame>", "<note>", "<trace>", "<on>", "<label>", "<br>", "<m>", "<v>"):
        assert raw not in html
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in html
    assert "&lt;frame&gt;" in html and "assert 1 &lt; 2 &amp; 3 &gt; 4" in html
    assert [scenario_status(s)[0] for s in report.scenarios] == ["red", "green", "amber", "red"]
    assert 'class="entry st-amber"' in html
    # every matrix link has its target
    import re

    for target in re.findall(r'href="#([^"]+)"', html):
        assert f'id="{target}"' in html


def test_latency_chart_svg():
    svg = charts.latency_strip("death_to_event", [0.3, 0.5, 0.4, 0.45, 2.0])
    assert svg.startswith("<svg") and svg.endswith("</svg>")
    assert "median 0.45 ms" in svg
    assert "death_to_event latency, ms" in svg
    assert svg.count("<circle") == 5
    wide = charts.latency_strip("t", [1.0, 10.0, 1000.0])
    assert "log scale" in wide
    assert charts.linear_ticks(0, 0.93) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert charts.linear_ticks(5.0, 5.0)[0] <= 5.0 <= charts.linear_ticks(5.0, 5.0)[-1]
    assert charts.log_ticks(3, 40) == [1, 2, 5, 10, 20, 50, 100]
    assert charts.log_ticks(3, 400) == [1, 10, 100, 1000]
    assert charts.latency_strip("none", []) == ""


# --------------------------------------------------------------------------
# compare and render
# --------------------------------------------------------------------------
def save(tmp_path, name, scenarios) -> Path:
    directory = tmp_path / name
    Report(RunInfo(id=name), scenarios).save_json(directory)
    return directory


def test_compare_detects_significant_regression(tmp_path, capsys):
    a = save(
        tmp_path,
        "a",
        [
            make_scenario("scenarios/t.py::test_segv", 19, 20, latency=lambda i: 0.4),
            make_scenario("scenarios/t.py::test_abort", 20, 20, fault="abort"),
            make_scenario("scenarios/t.py::test_gone", 5, 5, fault="gone"),
        ],
    )
    b = save(
        tmp_path,
        "b",
        [
            make_scenario("scenarios/t.py::test_segv", 8, 20, latency=lambda i: 0.6),
            # renamed test: matched by fault+profile
            make_scenario("scenarios/t2.py::test_abort_renamed", 19, 20, fault="abort"),
            make_scenario("scenarios/t.py::test_new", 1, 1, fault="new"),
        ],
    )
    assert harness_main(["compare", str(a), str(b)]) == 0
    text = capsys.readouterr().out
    assert "two-proportion z-test" in text
    assert "19/20" in text and "8/20" in text and "WORSE (significant)" in text
    assert "median 0.4 ms -> 0.6 ms  x1.50" in text
    assert "matched by fault+profile+mitigations" in text and "test_abort_renamed" in text
    assert "no significant change" in text
    assert "only in A:" in text and "test_gone" in text
    assert "only in B:" in text and "test_new" in text

    assert harness_main(["compare", str(a), str(b / "report.json"), "--fail-on-regression"]) == 1
    assert "significantly worse" in capsys.readouterr().err
    # the other way round it got better, which is no regression
    assert harness_main(["compare", str(b), str(a), "--fail-on-regression"]) == 0
    assert "better (significant)" in capsys.readouterr().out


def test_compare_methods_disagree_where_expected(tmp_path):
    """20/20 -> 15/20: the z-test calls it significant (p = 0.017), the two
    Wilson intervals (83.9–100% and 53.1–88.8%) overlap."""
    a = Report(RunInfo(id="a"), [make_scenario("t::x", 20, 20)])
    b = Report(RunInfo(id="b"), [make_scenario("t::x", 15, 20)])
    by_z = compare_reports(a, b, method="z")
    by_wilson = compare_reports(a, b, method="wilson")
    assert [d.verdict for d in by_z.deltas] == ["worse"]
    assert by_z.deltas[0].p_value == pytest.approx(0.0168, abs=5e-4)
    assert [d.verdict for d in by_wilson.deltas] == ["same"]
    assert "Wilson" in format_comparison(by_wilson)


def test_match_is_by_nodeid_first_and_never_ambiguous():
    a = Report(
        RunInfo(id="a"),
        [make_scenario("t::one", 1, 1), make_scenario("t::two", 1, 1), make_scenario("t::same", 1, 1, fault="f")],
    )
    b = Report(RunInfo(id="b"), [make_scenario("u::three", 1, 1), make_scenario("t::same", 1, 1, fault="g")])
    pairs, only_a, only_b = match_scenarios(a, b)
    # t::same matches by node id although its fault changed; "segv/per-node"
    # is shared by two scenarios of A, so u::three is not paired with either
    assert [(x.nodeid, y.nodeid, how) for x, y, how in pairs] == [("t::same", "t::same", "nodeid")]
    assert [s.nodeid for s in only_a] == ["t::one", "t::two"]
    assert [s.nodeid for s in only_b] == ["u::three"]


def test_render_regenerates_html(tmp_path, capsys):
    directory = save(tmp_path, "r", [make_scenario("scenarios/t.py::test_segv", 7, 8, latency=lambda i: i + 1.0)])
    assert not (directory / "report.html").exists()
    assert harness_main(["render", str(directory)]) == 0
    html = (directory / "report.html").read_text()
    assert "7/8 survived" in html and "<svg" in html
    # edit the data, render again from report.json
    data = json.loads((directory / "report.json").read_text())
    data["scenarios"][0]["claim"] = "a claim added later & re-rendered"
    (directory / "report.json").write_text(json.dumps(data))
    other = tmp_path / "elsewhere.html"
    assert harness_main(["render", str(directory / "report.json"), "-o", str(other)]) == 0
    assert "a claim added later &amp; re-rendered" in other.read_text()
    assert harness_main(["render", str(tmp_path / "missing")]) == 2


def test_python_dash_m_harness(tmp_path):
    a = save(tmp_path, "a", [make_scenario("t::x", 20, 20)])
    b = save(tmp_path, "b", [make_scenario("t::x", 2, 20)])
    done = subprocess.run(
        [sys.executable, "-m", "cloneguard.harness", "compare", str(a), str(b), "--fail-on-regression"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 1, done.stderr
    assert "WORSE (significant)" in done.stdout
    helped = subprocess.run(
        [sys.executable, "-m", "cloneguard.harness", "--help"], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert helped.returncode == 0 and "compare" in helped.stdout and "render" in helped.stdout


def test_report_round_trips_through_json(tmp_path):
    original = Report(
        RunInfo(id="x", host={"kernel": "6.1"}),
        [
            make_scenario(
                "t::x",
                3,
                4,
                latency=lambda i: math.pi * i,
                claim="c",
                notes=["n"],
                hangs=[Hang(summary="s", trial=3, stacks="st", lock="0x1", owner_tid=7, owner_node="/n")],
            )
        ],
    )
    original.save_json(tmp_path)
    loaded = load_report(tmp_path)
    assert loaded.to_dict() == original.to_dict()
    assert loaded.directory == tmp_path
    with pytest.raises(ValueError):
        Report.from_dict({"schema": "something-else"})


# --------------------------------------------------------------------------
# container deaths: counted on their own, shown first
# --------------------------------------------------------------------------
def _cells_with_deaths() -> Report:
    def cell(name, profile, outcomes):
        s = Scenario(nodeid=f"scenarios/test_x.py::{name}", name=name, fault="sigkill-outside", profile=profile)
        s.trials = [Trial(index=i, outcome=o, seed=i, details={"why": f"{o} {i}"}) for i, o in enumerate(outcomes)]
        return s

    return Report(
        run=RunInfo(id="r1"),
        scenarios=[
            cell("test_busy[per-node]", "per-node", ["survived", "hung", "survived", "crashed", "survived"]),
            cell("test_busy[shared]", "shared", ["survived"] * 5),
            cell("test_baseline", "threads", ["crashed"] * 5),  # thread mode: not counted
        ],
    )


def test_container_deaths_of_isolated_cells_are_counted_apart_from_other_outcomes():
    report = _cells_with_deaths()
    deaths = report.container_deaths()
    assert (deaths.successes, deaths.trials) == (1, 10)
    assert report.summary()["container_deaths"]["successes"] == 1


def test_the_summary_shows_container_deaths_first():
    from cloneguard.harness.report.summary import markdown

    text = markdown(_cells_with_deaths())
    headline = text.index("Container deaths (every node at once) in the isolated cells: **1** in 10 trials")
    assert headline < text.index("| scenario |")
    assert "| busy[per-node] | per-node | 5 | 1 | 3 |" in text
    listing = text[text.index("Every trial that did not survive") :]
    assert listing.index("trial 3 (seed 3), a container death") < listing.index("trial 1 (seed 1), hung")
    assert "**baseline**" not in listing


def test_the_html_report_shows_container_deaths_first():
    html = render_html(_cells_with_deaths())
    badge = html.index("1 container death in 10 isolated trials")
    assert badge < html.index("trials:")  # before the other totals
    assert '<div class="big death">1 container death</div>' in html


def test_a_small_rate_keeps_two_significant_digits():
    # A 95% upper bound of no container death in 9,000 trials is 0.043%,
    # which one decimal would print as 0.0%.
    upper = stats.proportion(0, 9000).high
    assert stats.percent(upper) == "0.043%"
    assert stats.percent(0.0) == "0.0%" and stats.percent(0.9951) == "99.5%" and stats.percent(0.0019) == "0.19%"
    assert stats.percent(None) == "–" and stats.percent(None, none="-") == "-"


def test_no_failed_test_is_not_said_in_red():
    from cloneguard.harness.report.model import Report, RunInfo, Scenario
    from cloneguard.harness.report.render import render_html

    report = Report(run=RunInfo(id="r"), scenarios=[Scenario(nodeid="t.py::test_ok", name="test_ok", outcome="passed")])
    html = render_html(report)
    assert '<span class="badge b-passed">1 passed</span>' in html
    assert '<span class="badge ">0 failed</span>' in html and 'b-failed">0 failed' not in html


def test_the_project_is_the_nearest_pyproject_up_to_the_root(tmp_path):
    from cloneguard.harness.report.env import project_name

    root = tmp_path / "checkout"
    pkg = root / "examples" / "robot"
    (pkg / "scenarios").mkdir(parents=True)
    (root / "pyproject.toml").write_text('[project]\nname = "outer"\n')
    (pkg / "pyproject.toml").write_text('[project]\nname = "my-robot"\n')
    assert project_name(pkg / "scenarios", root) == "my-robot"
    assert project_name(root / "examples", root) == "outer"
    (root / "pyproject.toml").write_text("[tool.pytest.ini_options]\n")
    assert project_name(root / "examples", root) == "checkout"  # no name: the root's directory


@pytest.mark.parametrize("pku", [True, False])
def test_the_host_line_says_whether_keys_protect_and_past_how_many_nodes_they_share(pku):
    report = Report(RunInfo(id="r", host={"cpu_model": "QEMU TCG CPU", "cpu_count": 2, "pku": pku}), [])
    html = render_html(report)
    assert ("PKU yes" in html and "up to 14" in html and "past 14, nodes share keys" in html) == pku
    assert ("PKU no" in html) == (not pku)


# --------------------------------------------------------------------------
# measurements in units other than ms
# --------------------------------------------------------------------------
def test_a_trials_measurements_keep_their_units_through_the_report(tmp_path):
    from cloneguard.harness.report.record import Resilience
    from cloneguard.harness.system_trials import Measure, _measurements

    scenario = Scenario(nodeid="scenarios/test_robot.py::test_replans", name="test_replans")
    resilience = Resilience(scenario)
    for i, replans in enumerate([2, 3, 2]):
        values = _measurements({"replans": Measure(replans, "count"), "get_map": 1.5 + i}, resilience)
        resilience.trial("survived", index=i, seed=i, latency_ms=values)
    assert scenario.units == {"replans": "count"} and scenario.unit("get_map") == "ms"
    with pytest.raises(ValueError, match="'replans' is in count, not MiB"):
        _measurements({"replans": Measure(1, "MiB")}, resilience)
    with pytest.raises(TypeError, match="mapping of measurements"):
        _measurements([1.0], resilience)  # type: ignore[arg-type]  # the wrong type is the point

    html = render_html(Report(RunInfo(id="u"), [scenario]))
    assert "Measurements" in html and "replans count</th>" in html and "get_map ms</th>" in html
    assert "replans, count" in html and "median 2 count" in html  # the chart's axis and median
    original = Report(RunInfo(id="u"), [scenario])
    original.save_json(tmp_path)
    assert load_report(tmp_path).scenarios[0].units == {"replans": "count"}
    text = format_comparison(compare_reports(original, original))
    assert "measured replans: median 2 count -> 2 count" in text and "latency get_map: median 2.5 ms" in text


def test_units_reach_the_report_a_session_writes(pytester, tmp_path, report_root):
    """The record rides on the teardown report to the session that writes
    report.json: the units go with it, not only the values."""
    out = tmp_path / "run"
    result = run_session(
        pytester,
        "--report-dir",
        str(out),
        "scenarios",
        files={
            "test_units.py": """
        from cloneguard.harness.system_trials import Measure, _measurements

        def test_scans(resilience):
            for i in range(3):
                values = _measurements({"scans": Measure(19 * (i + 1), "count"), "status": 1.0}, resilience)
                resilience.trial("survived", index=i, seed=i, latency_ms=values)
    """
        },
    )
    result.assert_outcomes(passed=1)
    (scenario,) = json.loads((out / "report.json").read_text())["scenarios"]
    assert scenario["units"] == {"scans": "count"}
    html = (out / "report.html").read_text()
    assert "<h4>Measurements</h4>" in html and "Latency (ms)" not in html
    assert "scans count</th>" in html and "status ms</th>" in html and "median 38.0 count" in html
