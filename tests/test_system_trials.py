"""Seeded trials of a user's own System (harness/system_trials.py): how an
outcome is judged and recorded, what a watched topic's facts and timeline
say, and, as a user runs them, failed and hung trials in the report."""

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from types import SimpleNamespace
from typing import Any

import pytest

from cloneguard.harness.client import Received, Recorder
from cloneguard.harness.node_memory import MemorySample
from cloneguard.harness.report.system_view import timeline_svg
from cloneguard.harness.system import Fault, NodeSpec
from cloneguard.harness.system_trials import fault_record, profile_of, timeline, topic_facts

MS = 1_000_000
MiB = 1 << 20


@pytest.mark.parametrize(
    "args, profile",
    [
        ([], "threads"),
        (["--use_multi_threaded_executor"], "threads"),
        (["--isolated"], "shared"),
        (["--isolated", "--profile", "per-node"], "per-node"),
        (["--isolated", "--profile=per-node", "--cgroups"], "per-node"),
        (["--isolated", "--profile", "shared"], "shared"),
    ],
)
def test_the_reports_profile_follows_the_container_arguments(args, profile):
    assert profile_of(args) == profile


def test_the_harness_knows_the_containers_default_profile():
    from cloneguard.container.isolated import profiles
    from cloneguard.harness.system_trials import DEFAULT_PROFILE

    assert DEFAULT_PROFILE == profiles.DEFAULT


@pytest.mark.parametrize(
    "what, ends", [("SIGKILL", True), ("SIGSEGV", True), ("SIGTERM", True), ("SIGCONT", False), ("freeze 1 s", False)]
)
def test_a_fault_ends_the_node_when_its_signal_does(what, ends):
    assert Fault("/n", what, 0, 0, 1).ends_the_node is ends


def _system(stamps_ms: dict[str, list[float]], start_ns: int, memory: dict[str, list[MemorySample]] | None = None):
    watched = {}
    for name, stamps in stamps_ms.items():
        rec = Recorder(name)
        rec._items.extend(Received(None, start_ns + int(ms * MS)) for ms in stamps)
        watched[name] = rec

    def memory_by_node(since_ns: int, until_ns: int) -> dict[str, list[MemorySample]]:
        got = {
            node: [s for s in samples if since_ns <= s.at_ns <= until_ns] for node, samples in (memory or {}).items()
        }
        return {node: samples for node, samples in got.items() if samples}

    return SimpleNamespace(watched=watched, memory_by_node=memory_by_node)


def test_topic_facts_count_the_window_only_and_its_edges_as_gaps():
    start = 10_000 * MS
    # 10 Hz for 1 s, then nothing for 0.5 s; one message before the window
    system = _system({"/odom": [-50, *range(0, 1000, 100)], "/silent": []}, start)
    facts = topic_facts(system, start, start + 1500 * MS)
    assert facts["/odom"] == {"messages": 10, "rate_hz": pytest.approx(10 / 1.5, abs=1e-3), "longest_gap_s": 0.6}
    assert facts["/silent"] == {"messages": 0, "rate_hz": 0.0, "longest_gap_s": 1.5}


def test_a_timeline_bins_whole_bins_and_places_the_faults():
    start = 10_000 * MS
    system = _system({"/odom": [5, 15, 25, 150, 330, 349]}, start)
    fault = Fault("/planner", "SIGKILL", start + 120 * MS, start + 120 * MS, 3)
    tl = timeline(system, start, start + 350 * MS)
    # three whole 100 ms bins: the last 50 ms (a cut bin) are left out
    assert tl == {"bin_ms": 100, "topics": {"/odom": [3, 1, 0]}}
    assert fault_record(fault, start) == {
        "node": "/planner", "kind": "SIGKILL", "what": "SIGKILL", "from_ms": 120.0, "to_ms": 120.0
    }  # fmt: skip
    frozen = Fault("/map", "freeze 0.5 s", start + 10 * MS, start + 510 * MS, 4)
    assert fault_record(frozen, start)["kind"] == "freeze" and fault_record(frozen, start)["to_ms"] == 510.0


def test_a_timeline_draws_each_nodes_memory_from_its_last_report_before():
    start = 10_000 * MS
    samples = [(-2500, 9), (-900, 1), (-500, 1), (100, 2), (250, 40), (900, 3)]
    leak = [MemorySample(start + ms * MS, mib * MiB, 0) for ms, mib in samples]
    # Killed before its first report in the trial: its last one before it.
    killed = [MemorySample(start - 700 * MS, 5 * MiB, 64 * MiB)]
    system = _system({"/odom": [5, 150, 250]}, start, {"/leak": leak, "/killed": killed})
    tl = timeline(system, start, start + 300 * MS)
    assert tl["memory_mib"] == {
        "/killed": [[-700.0, 5.0]],
        "/leak": [[-500.0, 1.0], [100.0, 2.0], [250.0, 40.0]],  # the last before the trial, then the window's
    }
    svg = timeline_svg(tl, [])
    assert ">/leak memory<" in svg and ">40 MiB<" in svg and ">/killed memory<" in svg
    assert svg.count("<polyline") == 3 and svg.count("<circle") == 4
    assert "memory_mib" not in timeline(_system({"/odom": [5]}, start), start, start + 300 * MS)


USER_SCENARIOS = textwrap.dedent("""
    import signal

    from std_msgs.msg import Float64

    from cloneguard.harness.system import NodeSpec, rate

    ROBOT = [
        NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 20.0}),
        NodeSpec("demo_robot", "demo_robot::Planner"),
    ]


    def test_a_claim_that_cannot_hold(system_factory, system_trials):
        robot = system_factory(ROBOT)
        odom = robot.topic(Float64, "/odom")
        odom.wait_count(3, timeout=10)

        def trial(t):
            died = robot.kill("/planner", signal.SIGSEGV)
            robot.wait_crashed("/planner")
            odom.wait_count(len(odom) + 4, timeout=10)
            assert rate(odom, died) >= 1000.0, "odometry is not at 1 kHz"

        system_trials(robot, trial, fault="planner SIGKILL", claim="odometry at 1 kHz", at_least=0.99)


    def test_a_topic_that_never_speaks(system_factory, system_trials):
        robot = system_factory(ROBOT)

        def trial(t):
            robot.topic(Float64, "/nobody_publishes_this").wait_count(1, timeout=0.3)

        system_trials(robot, trial, fault="none", claim="a silent topic speaks")
""")


def test_failed_and_hung_trials_are_recorded_with_their_cause_first(tmp_path):
    (tmp_path / "scenarios").mkdir()
    (tmp_path / "scenarios" / "test_user.py").write_text(USER_SCENARIOS)
    report = tmp_path / "report"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "scenarios", "--trials", "2",
           "--seed", "7", "--report-dir", str(report)]  # fmt: skip
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=300, env=dict(os.environ))
    assert proc.returncode == 1, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "1 failed, 1 passed" in proc.stdout, proc.stdout[-3000:]
    run = json.loads((report / "report.json").read_text())
    by_name = {s["name"]: s for s in run["scenarios"]}

    cannot = by_name["test_a_claim_that_cannot_hold"]
    assert [t["outcome"] for t in cannot["trials"]] == ["failed", "failed"]
    assert all(t["details"]["why"] == "odometry is not at 1 kHz" for t in cannot["trials"])
    assert all([(f["node"], f["kind"]) for f in t["details"]["faults"]] == [("/planner", "SIGSEGV")]
               for t in cannot["trials"])  # fmt: skip
    assert all(t["details"]["topics"]["/odom"]["messages"] >= 4 for t in cannot["trials"])
    for t in cannot["trials"]:  # the container's events of the trial, among its facts
        [crashed] = [ev for ev in t["details"]["events"] if ev["event"] == "CRASHED"]
        assert crashed["node"] == "/planner" and "SIGSEGV" in crashed["what"] and crashed["at_ms"] >= 0
    assert [t["index"] for t in cannot["trials"]] == [0, 1]
    assert all("timeline" in t["details"] for t in cannot["trials"])  # every non-survivor is drawn
    survived = [e for e in cannot["expectations"] if e["outcome"] == "survived"]
    assert survived and survived[0]["met"] is False
    assert cannot["outcome"] == "failed"

    silent = by_name["test_a_topic_that_never_speaks"]
    assert [t["outcome"] for t in silent["trials"]] == ["hung", "hung"]
    assert "0 of 1 messages" in silent["trials"][0]["details"]["why"]
    assert silent["outcome"] == "passed"  # no rate was promised
    # a hung trial gets the diagnosis the project's own get: every thread's stack
    assert [h["trial"] for h in silent["hangs"]] == [0, 1]
    assert all("no thread waits on a lock" in h["summary"] and "Thread " in h["stacks"] for h in silent["hangs"])

    html = (report / "report.html").read_text()
    assert "odometry is not at 1 kHz" in html and "Topics during the trials" in html
    assert "Timeline of trial 0 (failed)" in html and "Faults by node" in html
    assert "SIGSEGV → /planner at " in html  # the trial's faults in words
    assert "CRASHED /planner (pid " in html  # and its events
    # a trial that did not survive keeps the crash report of the node its fault ended
    for t in cannot["trials"]:
        [(who, written)] = t["details"]["crash_reports"].items()
        assert who.startswith("/planner (pid ") and "caught SIGSEGV" in written and "native stack:" in written
    assert "crash report of /planner (pid " in html
    assert "{&quot;why&quot;" not in html  # facts in words, not a JSON blob

    # the same --seed gives the same trials
    again = report.parent / "again"
    cmd[cmd.index("--report-dir") + 1] = str(again)
    subprocess.run([*cmd, "-k", "never_speaks"], cwd=tmp_path, capture_output=True, timeout=300, env=dict(os.environ))
    replay = json.loads((again / "report.json").read_text())["scenarios"][0]
    assert [t["seed"] for t in replay["trials"]] == [t["seed"] for t in silent["trials"]]


def _until_held(proc) -> tuple[str, int]:
    """What a held run printed up to its "holding it until" line, and the
    held container's pid."""
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if line.startswith("holding it until"):
            break
    text = "".join(seen)
    return text, int(text.split("container pid ")[1].split()[0])


def test_a_replayed_trial_stops_there_and_holds_its_container(tmp_path):
    """--trial-seed replays one trial; --hold-failed keeps the container of
    the first that does not survive running; --container-arg reaches it."""
    (tmp_path / "scenarios").mkdir()
    (tmp_path / "scenarios" / "test_user.py").write_text(USER_SCENARIOS)
    report = tmp_path / "report"
    test = "scenarios/test_user.py::test_a_claim_that_cannot_hold"
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", test, "--trial-seed", "42",
           "--hold-failed", "5", "--container-arg=--profile=shared", "--report-dir", str(report)]  # fmt: skip
    proc = subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        text, pid = _until_held(proc)
        assert "trial 0 (--trial-seed 42) did not survive: failed: odometry is not at 1 kHz" in text, text
        os.kill(pid, 0)  # held: still running
        log = text.split("container log: ")[1].split()[0]
    finally:
        rest, _ = proc.communicate(timeout=120)
    assert proc.returncode == 1, text + rest
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)  # stopped once the test ended
    with open(log) as fh:
        assert "profile shared" in fh.read()
    [scenario] = json.loads((report / "report.json").read_text())["scenarios"]
    assert [(t["index"], t["seed"], t["outcome"]) for t in scenario["trials"]] == [(0, 42, "failed")]


def test_reproduce_runs_a_scenario_of_yours_through_pytest():
    from argparse import Namespace

    from cloneguard.harness.reproduce import is_node_id, scenario_command

    assert is_node_id("scenarios/test_robot.py::test_planner") and not is_node_id("segfault-gil-held")
    args = Namespace(
        fault="scenarios/test_robot.py::test_planner", seed=3, trial_seed=None, trials=50, no_wait=False,
        container_arg=["--jemalloc"], container_exe=None, profile=None, allocator=None,
    )  # fmt: skip
    assert scenario_command(args)[1:] == [
        "-m", "pytest", "scenarios/test_robot.py::test_planner", "-p", "no:cacheprovider", "--seed", "3",
        "--trials", "50", "--hold-failed", "inf", "--container-arg=--jemalloc",
    ]  # fmt: skip
    args.trial_seed, args.no_wait = 99, True
    assert scenario_command(args)[-5:] == ["--trial-seed", "99", "--hold-failed", "0", "--container-arg=--jemalloc"]
    args.profile = "shared"
    with pytest.raises(SystemExit, match="for the rig's faults"):
        scenario_command(args)


def test_ctrl_c_on_a_held_reproduce_stops_it_cleanly(tmp_path):
    """As at a terminal: Ctrl-C reaches reproduce and its pytest (one
    process group); pytest stops the held container and writes its
    report, and reproduce prints no traceback of its own."""
    (tmp_path / "scenarios").mkdir()
    (tmp_path / "scenarios" / "test_user.py").write_text(USER_SCENARIOS)
    test = "scenarios/test_user.py::test_a_claim_that_cannot_hold"
    cmd = [sys.executable, "-m", "cloneguard.harness", "reproduce", test, "--trial-seed", "42"]
    proc = subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)  # fmt: skip
    try:
        text, pid = _until_held(proc)
        assert "holding it until Ctrl-C" in text
        os.killpg(proc.pid, signal.SIGINT)
    finally:
        rest, _ = proc.communicate(timeout=120)
    assert "Traceback" not in text + rest, text + rest
    assert proc.returncode != 0  # interrupted, not passed
    with pytest.raises(ProcessLookupError):
        os.kill(pid, 0)
    assert "resilience report" in rest  # pytest finished its session: the report is written


def test_the_rate_has_the_fields_the_docs_name():
    from dataclasses import fields
    from pathlib import Path

    from cloneguard.harness.report.stats import Proportion

    docs = (Path(__file__).resolve().parent.parent / "docs" / "testing-your-nodes.md").read_text()
    said = docs.split("It returns")[1].split(")")[0]
    assert {f.name for f in fields(Proportion)} == {"successes", "trials", "rate", "low", "high"}
    assert all(f"`{f.name}`" in said for f in fields(Proportion)), said


def _event(kind: str, uid: int, name: str = "", pid: int = 0, **fields):
    from cloneguard_interfaces.msg import ComponentEvent

    ev = ComponentEvent(event_type=getattr(ComponentEvent, kind), unique_id=uid, full_node_name=name, pid=pid)
    for key, value in fields.items():
        setattr(ev, key, value)
    return ev


def test_a_repaired_event_names_the_node_whose_death_left_it():
    """A REPAIRED that leaves out the dead node's name and pid (as the
    container's did before its manager kept its dead nodes' names) gets
    them in the trial's facts from that node's own events, by unique_id."""
    from cloneguard.harness.report.model import Trial
    from cloneguard.harness.report.system_view import trial_facts
    from cloneguard.harness.system_trials import container_events

    start = 10_000 * MS
    said = "the Python Lock my_pkg.shared.LOCK, held by /filter (pid 41, thread 41) when its process died, ..."
    events = Recorder("events")
    for at_ms, ev in [
        (-900, _event("LOADED", 2, "/filter", 41)),
        (-800, _event("LOADED", 3, "/planner", 42)),
        (100, _event("CRASHED", 2, "/filter", 41, error_message="killed by SIGKILL")),
        (120, _event("REPAIRED", 2, repaired_state="python-lock", error_message=said)),
        (130, _event("REPAIRED", 9, repaired_state="intra-queue", error_message="a queue")),  # a node never seen
    ]:
        events._items.append(Received(ev, start + at_ms * MS))
    system: Any = SimpleNamespace(client=SimpleNamespace(events=events))  # all container_events reads
    crashed, repaired, unknown = container_events(system, start, start + 1000 * MS)
    assert (crashed["node"], crashed["pid"]) == ("/filter", 41)
    assert repaired == {
        "at_ms": 120.0, "event": "REPAIRED", "node": "/filter", "pid": 41, "repaired": "python-lock", "what": said
    }  # fmt: skip
    assert (unknown["node"], unknown["pid"]) == ("", 0)

    facts = trial_facts(Trial(index=0, outcome="survived", details={"events": [crashed, repaired, unknown]}))
    assert "CRASHED /filter (pid 41) at 100 ms: killed by SIGKILL" in facts
    assert "REPAIRED python-lock left by /filter (pid 41) at 120 ms: the Python Lock" in facts
    assert "REPAIRED intra-queue at 130 ms: a queue" in facts and "pid 0" not in facts


def test_a_lifecycle_node_reloaded_again_and_again_takes_a_transition_first(system_factory):
    """change_state as the first call after each reload: a lost request
    is sent again only once get_state says the transition was not made
    (talk.Talker.change_state), so it is never made twice."""
    robot = system_factory([NodeSpec("demo_robot", "demo_robot::Navigator")])
    for _ in range(4):
        assert robot.change_state("/navigator", "configure", timeout=10)
        assert robot.get_state("/navigator") == "inactive"
        assert not robot.change_state("/navigator", "configure")  # made once: a second is refused
        since = time.monotonic_ns()
        robot.kill("/navigator", signal.SIGKILL)
        robot.recover(since)


def test_a_lifecycle_node_reloaded_again_and_again_answers_get_state(system_factory):
    """A reloaded node is a new instance: back unconfigured, under a new
    unique_id and pid. Its dead predecessors' servers stand in the graph a
    while longer (their participants' lease), so the service looks offered
    before the harness has matched the new one: a request sent then is lost.
    get_state, which changes nothing, sends it again until answered (lost
    in 3 runs of 3 before it did)."""
    robot = system_factory([NodeSpec("demo_robot", "demo_robot::Navigator")])
    seen = set()
    for _ in range(4):
        running = robot.node("/navigator")
        assert (running.unique_id, running.pid) not in seen
        seen.add((running.unique_id, running.pid))
        assert robot.get_state("/navigator", timeout=5) == "unconfigured"
        assert robot.change_state("/navigator", "configure") and robot.change_state("/navigator", "activate")
        assert robot.get_state("/navigator") == "active"
        since = time.monotonic_ns()
        robot.kill("/navigator", signal.SIGKILL)
        robot.recover(since)
