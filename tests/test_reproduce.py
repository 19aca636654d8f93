"""``python -m cloneguard.harness reproduce`` replays every fault the scenarios inject:
the harness finds the fault registry (faults/trials.py) through its entry
point, and each fault's trial runs from a given seed."""

import os
import re
import shutil
import subprocess
import sys

import pytest

from cloneguard.faults.trials import FAULTS, MALLOC_ALLOCATORS
from cloneguard.harness.report.model import TRIAL_OUTCOMES
from cloneguard.harness.reproduce import registry


def test_the_harness_finds_the_registry_the_scenarios_use():
    faults, allocators = registry()
    assert faults is FAULTS and allocators is MALLOC_ALLOCATORS


@pytest.mark.timeout(180)
@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_every_fault_can_be_replayed_from_a_seed(fault):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "cloneguard.harness",
            "reproduce",
            fault,
            "--trials",
            "1",
            "--trial-seed",
            "4242",
            "--no-wait",
        ],
        capture_output=True,
        text=True,
        timeout=170,
    )
    if "needs a memory cgroup, and none can be made here" in proc.stderr:  # an out-of-memory fault
        shutil.rmtree(re.findall(r"^logs: (\S+)", proc.stdout, re.M)[0])
        pytest.skip(proc.stderr.strip().splitlines()[-1])
    # One trial ran from that seed and was judged; whatever its outcome,
    # the command says it (0: survived, 1: stopped at the one that did not).
    outcomes = "|".join(TRIAL_OUTCOMES)
    assert re.search(rf"^trial 0 seed 4242: ({outcomes})", proc.stdout, re.M), proc.stdout + proc.stderr
    survived = "seed 4242: survived" in proc.stdout
    assert proc.returncode == (0 if survived else 1)
    # Its logs are kept only when there is something to look at.
    [logs] = re.findall(r"^logs: (\S+)", proc.stdout, re.M)
    assert os.path.isdir(logs) is not survived, proc.stdout
    if not survived:
        shutil.rmtree(logs)


def _reproduce(*args, timeout=60):
    return subprocess.run(
        [sys.executable, "-m", "cloneguard.harness", "reproduce", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


@pytest.mark.parametrize("count", ["0", "-3", "many"])
def test_a_trial_count_below_one_is_a_usage_error(count):
    proc = _reproduce("segfault-gil-held", "--trials", count)
    assert proc.returncode == 2 and "argument --trials: a trial count is" in proc.stderr, proc.stderr
    assert "trials survived" not in proc.stdout


def test_another_container_executable_is_the_one_started(tmp_path):
    exe = tmp_path / "component_container"
    exe.write_text("#!/bin/sh\necho 'the other container' >&2\nexit 3\n")
    exe.chmod(0o755)
    proc = _reproduce("segfault-gil-held", "--trials", "1", "--no-wait", "--container-exe", str(exe))
    assert proc.returncode != 0 and "trial 0" not in proc.stdout
    assert "the other container" in proc.stdout + proc.stderr, proc.stdout + proc.stderr
    [logs] = re.findall(r"^logs: (\S+)", proc.stdout, re.M)  # kept: the start failed
    shutil.rmtree(logs)


def test_no_wait_says_it_stops_the_stuck_container_and_offers_no_debugger(capsys, tmp_path):
    from cloneguard.harness.reproduce import _report_stuck

    class Proc:
        pid, log_path = 4321, tmp_path / "container.log"

        def alive(self):
            return True

    class Stuck:
        proc = Proc()

    class Out:
        outcome, details, diagnosis = "hung", {"why": "no heartbeat"}, None

    _report_stuck(Stuck(), Out(), tmp_path, wait=False)  # type: ignore[arg-type]  # what it reads of both
    text = capsys.readouterr().out
    assert "stopping it now (--no-wait)" in text and "gdb -p" not in text and "Ctrl-C" not in text
