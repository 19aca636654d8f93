"""Faults of yours by name (harness/named_faults.py): a package declares
them in the entry point group, ``reproduce NAME`` replays them through
pytest like a scenario of yours, and a bad declaration is said plainly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from argparse import Namespace

import pytest

from cloneguard.harness import named_faults
from cloneguard.harness.reproduce import scenario_command

DEMO_FAULT = "planner-holding-a-lock"  # examples/demo_robot/pyproject.toml


def _declare(tmp_path, monkeypatch, name: str, value: str) -> None:
    """A distribution on sys.path declaring one entry point in the group."""
    info = tmp_path / "someones_faults-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: someones-faults\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{named_faults.GROUP}]\n{name} = {value}\n")
    monkeypatch.syspath_prepend(str(tmp_path))


def test_the_demo_robots_fault_is_found_by_its_name():
    assert DEMO_FAULT in named_faults.names()
    fault = named_faults.load(DEMO_FAULT)
    assert isinstance(fault, named_faults.NamedFault) and fault.at_least == 0.99


def test_an_unknown_name_says_which_there_are():
    with pytest.raises(LookupError, match=f"no fault 'nope' in the entry point group .*{DEMO_FAULT}"):
        named_faults.load("nope")


def test_a_declaration_that_is_not_a_named_fault_is_refused(tmp_path, monkeypatch):
    _declare(tmp_path, monkeypatch, "not-a-fault", "json:dumps")
    with pytest.raises(TypeError, match="'not-a-fault' = json:dumps is a function, not a NamedFault"):
        named_faults.load("not-a-fault")


def test_one_name_declared_twice_is_refused(tmp_path, monkeypatch):
    _declare(tmp_path, monkeypatch, DEMO_FAULT, "json:dumps")
    with pytest.raises(LookupError, match=f"2 packages declare the fault '{DEMO_FAULT}'"):
        named_faults.load(DEMO_FAULT)


def test_reproduce_runs_a_named_fault_as_the_harness_scenario_of_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = Namespace(
        fault=DEMO_FAULT, seed=3, trial_seed=None, trials=50, no_wait=True,
        container_arg=[], container_exe=None, profile=None, allocator=None,
    )  # fmt: skip
    assert scenario_command(args)[1:] == [
        "-m", "pytest", str(named_faults.SCENARIO), f"--named-fault={DEMO_FAULT}", "--import-mode=importlib",
        f"--rootdir={tmp_path}", "-c", os.devnull, "-p", "no:cacheprovider", "--seed", "3", "--trials", "50",
        "--hold-failed", "0",
    ]  # fmt: skip
    (tmp_path / "pyproject.toml").write_text("[tool.pytest.ini_options]\n")  # your project's, not cloneguard's
    assert scenario_command(args)[7:9] == ["-c", str(tmp_path / "pyproject.toml")]


def test_a_named_fault_is_replayed_and_reported_where_it_is_run(tmp_path):
    cmd = [sys.executable, "-m", "cloneguard.harness", "reproduce", DEMO_FAULT, "--trials", "2", "--no-wait"]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    [config] = [line for line in proc.stdout.splitlines() if line.startswith("configfile:")]
    assert config.endswith("dev/null"), config  # not cloneguard's pyproject.toml: there is none here
    [scenario] = json.loads((tmp_path / "reports" / "latest" / "report.json").read_text())["scenarios"]
    assert scenario["fault"] == "planner SIGKILL holding a Python lock"
    assert [t["outcome"] for t in scenario["trials"]] == ["survived", "survived"]
    for t in scenario["trials"]:
        assert [(f["node"], f["kind"]) for f in t["details"]["faults"]] == [("/planner", "SIGKILL at python-lock")]


def test_reproduce_names_the_faults_of_yours_when_the_name_is_unknown():
    proc = subprocess.run(
        [sys.executable, "-m", "cloneguard.harness", "reproduce", "nope"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode != 0 and f"yours: {DEMO_FAULT}" in proc.stderr, proc.stderr
