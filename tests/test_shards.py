"""One report from many processes: pytest-xdist workers, and shards merged.

The scenarios here are stand-ins whose outcome is a function of the trial's
seed, so that which trials ran, with which seeds, is all that can differ
between an unsharded run, its shards merged, and an xdist run.
"""

from __future__ import annotations

import json

import pytest
from test_report import plugin_args

from cloneguard.harness.__main__ import main as harness_main
from cloneguard.harness.report.merge import MergeError, merge_reports
from cloneguard.harness.report.model import Report, load_report

pytest_plugins = ["pytester"]

CELLS = """
from cloneguard.harness.rig import Outcome

def by_seed(seed, index):
    return Outcome("survived" if seed % 7 else "hung", details={"index": index})

def test_cell(resilience, run_trials):
    resilience.describe(fault="stand-in", profile="p", claim="outcome decided by the seed")
    resilience.note(f"planned {run_trials(by_seed, lambda out: None, quick=11, deep=11)}")
    resilience.expect_rate("survived", at_least=0.5)

def test_unmet(resilience, run_trials):
    run_trials(by_seed, lambda out: None, quick=11, deep=11)
    resilience.expect_rate("survived", at_least=1.0)

def test_single(resilience, record_trial, trial_plan):
    [(index, seed)] = trial_plan(1, 1)
    record_trial(index, seed, Outcome("survived"))
"""


@pytest.fixture
def cells(pytester):
    pytester.mkdir("scenarios").joinpath("test_cells.py").write_text(CELLS)
    return pytester


def run(pytester, out, *args) -> Report:
    pytester.runpytest(
        *plugin_args(), "-p", "no:cacheprovider", "--report-dir", str(out), "--seed", "5", *args, "scenarios"
    )
    return load_report(out)


def trials_of(report) -> dict:
    return {s.nodeid: [(t.index, t.seed, t.outcome) for t in s.trials] for s in report.scenarios}


def test_three_shards_merged_are_the_unsharded_run(cells, tmp_path):
    whole = run(cells, tmp_path / "whole")
    shards = [run(cells, tmp_path / f"shard{k}", "--shard", f"{k}/3") for k in (1, 2, 3)]
    for k, shard in enumerate(shards, 1):
        assert shard.run.shard == f"{k}/3"
        assert all(e.met is None for s in shard.scenarios for e in s.expectations)
        cell = next(s for s in shard.scenarios if s.name == "test_cell")
        assert [t.index % 3 for t in cell.trials] == [k - 1] * len(cell.trials)
        assert cell.notes == ["planned 11"]  # the whole run's count, what picks a floor
    single = {s.name: s.outcome for s in shards[1].scenarios}["test_single"]
    assert single == "skipped"  # its one trial fell to shard 1

    merged = merge_reports(shards)
    assert trials_of(merged) == trials_of(whole)
    assert len(trials_of(whole)["scenarios/test_cells.py::test_cell"]) == 11
    by_name = {s.name: s for s in merged.scenarios}
    assert [e.met for e in by_name["test_cell"].expectations] == [True]
    assert [e.met for e in by_name["test_unmet"].expectations] == [False]
    assert by_name["test_unmet"].outcome == "failed" and by_name["test_single"].outcome == "passed"
    assert {s.name: s.outcome for s in whole.scenarios} == {s.name: s.outcome for s in merged.scenarios}
    assert [sh["shard"] for sh in merged.run.shards] == ["1/3", "2/3", "3/3"]


def test_merge_command_writes_a_report_and_fails_on_unmet(cells, tmp_path, capsys):
    parts = [tmp_path / f"s{k}" for k in (1, 2)]
    for k, out in enumerate(parts, 1):
        run(cells, out, "--shard", f"{k}/2")
    code = harness_main(["merge", *map(str, parts), "--out", str(tmp_path / "merged")])
    assert code == 1  # test_unmet's expectation is not met
    merged = load_report(tmp_path / "merged")
    assert {"report.json", "report.html", "junit.xml"} <= {p.name for p in (tmp_path / "merged").iterdir()}
    assert sum(len(s.trials) for s in merged.scenarios) == 11 + 11 + 1
    assert "FAILED scenarios/test_cells.py::test_unmet" in capsys.readouterr().err


def test_merge_refuses_other_commits_overlaps_and_other_plans(cells, tmp_path):
    a = run(cells, tmp_path / "a", "--shard", "1/2")
    b = run(cells, tmp_path / "b", "--shard", "2/2")
    b.run.git = {**b.run.git, "commit": "0" * 40}
    with pytest.raises(MergeError, match="different commits"):
        merge_reports([a, b])
    assert merge_reports([a, b], allow_mixed_commits=True).run.shards[1]["commit"] == "0" * 40
    with pytest.raises(MergeError, match="same shard"):
        merge_reports([a, a])
    c = run(cells, tmp_path / "c", "--shard", "2/2", "--trials", "4")
    with pytest.raises(MergeError, match="same --seed made different trial plans"):
        merge_reports([a, c])
    whole = run(cells, tmp_path / "whole")
    with pytest.raises(MergeError, match="run twice"):
        merge_reports([whole, a])


def test_runs_of_other_seeds_merge_as_independent_trials(cells, tmp_path):
    five = run(cells, tmp_path / "five")  # --seed 5
    six = [run(cells, tmp_path / f"six{k}", "--seed", "6", "--shard", f"{k}/2") for k in (1, 2)]
    seven = run(cells, tmp_path / "seven", "--seed", "7", "--trials", "3")
    merged = merge_reports([five, *six, seven])
    assert merged.run.plan == {"seed": [5, 6, 7], "deep": False, "trials": [None, None, 3]}
    assert [sh["seed"] for sh in merged.run.shards] == [5, 6, 6, 7]
    cell = next(s for s in merged.scenarios if s.name == "test_cell")
    # every trial of every run, numbered anew seed by seed, each its own seed
    expected = [
        (seed, t.index, t.seed, t.outcome)
        for seed, parts in ((5, [five]), (6, six), (7, [seven]))
        for t in sorted(
            (t for r in parts for s in r.scenarios if s.name == "test_cell" for t in s.trials), key=lambda t: t.index
        )
    ]
    assert len(expected) == 11 + 11 + 3
    assert [(t.index, t.seed, t.outcome) for t in cell.trials] == [
        (i, seed, outcome) for i, (_, _, seed, outcome) in enumerate(expected)
    ]
    assert [t.details["run"] for t in cell.trials[10:12]] == ["--seed 5, trial 10", "--seed 6, trial 0"]
    survived = sum(1 for *_, o in expected if o == "survived")
    [expectation] = cell.expectations
    assert (expectation.successes, expectation.trials) == (survived, 25)
    with pytest.raises(MergeError, match="not merged again"):
        merge_reports([merged, five])
    with pytest.raises(MergeError, match="run twice"):
        merge_reports([five, six[0], five])


def test_bad_shard_is_a_usage_error(cells, tmp_path):
    result = cells.runpytest(*plugin_args(), "--shard", "4/3", "scenarios")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    assert "K must be between 1 and N" in result.stderr.str()


@pytest.mark.parametrize("count", ["0", "-1"])
def test_a_trial_count_below_one_is_a_usage_error(cells, count):
    result = cells.runpytest(*plugin_args(), "--trials", count, "scenarios")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    assert "argument --trials: a trial count is at least 1" in result.stderr.str()


def test_xdist_workers_make_one_report(cells, tmp_path):
    pytest.importorskip("xdist")
    serial = run(cells, tmp_path / "serial")
    parallel = run(cells, tmp_path / "parallel", "-n", "2")
    assert parallel.run.workers == 2 and serial.run.workers == 0
    assert trials_of(parallel) == trials_of(serial)
    assert {s.name: s.outcome for s in parallel.scenarios} == {s.name: s.outcome for s in serial.scenarios}
    assert {s.name: [e.met for e in s.expectations] for s in parallel.scenarios} == {
        "test_cell": [True],
        "test_unmet": [False],
        "test_single": [],
    }
    data = json.loads((tmp_path / "parallel" / "report.json").read_text())
    assert data["summary"]["tests"] == 3
    junit = (tmp_path / "parallel" / "junit.xml").read_text()
    assert junit.count("<testcase") == 3


UNANSWERED = """
from cloneguard.harness.client import HarnessTimeout
from cloneguard.harness.rig import Outcome


class StandInRig:
    def not_survived(self, why):
        return Outcome("hung", details={"why": why})


def stuck_every_third(seed, index):
    if index % 3 == 2:
        raise HarnessTimeout("no answer from /ComponentManager/_container/load_node within 15.0 s")
    return Outcome("survived")


def test_cell(resilience, run_trials):
    resilience.describe(fault="stand-in", profile="p", claim="a load goes unanswered every third trial")
    run_trials(stuck_every_third, lambda out: None, quick=6, deep=6, rig=StandInRig())
"""


def test_a_trial_whose_request_goes_unanswered_is_a_hang_not_an_error(pytester, tmp_path):
    pytester.mkdir("scenarios").joinpath("test_unanswered.py").write_text(UNANSWERED)
    report = run(pytester, tmp_path / "out")
    [cell] = report.scenarios
    assert cell.outcome == "passed"
    assert [t.outcome for t in cell.trials] == ["survived", "survived", "hung"] * 2
    assert cell.trials[2].details["why"].startswith("the trial's request went unanswered: no answer from")
