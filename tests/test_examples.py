"""examples/: a package of nodes outside cloneguard (installed by
scripts/setup.sh) and its scenarios, written against the public test API
only (harness/system.py), run as a user runs them."""

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DEMO = REPO / "examples" / "demo_robot"


def test_the_demo_robots_scenarios_pass_and_write_a_report(tmp_path):
    report = tmp_path / "report"
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "scenarios", "--report-dir", str(report)],
        cwd=DEMO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "9 passed" in proc.stdout
    run = json.loads((report / "report.json").read_text())
    outcomes = {s["nodeid"].split("::", 1)[1]: s["outcome"] for s in run["scenarios"]}
    assert outcomes == {
        "test_odometry_and_the_map_outlive_the_planner[SIGSEGV]": "passed",
        "test_odometry_and_the_map_outlive_the_planner[SIGKILL]": "passed",
        "test_the_rest_outlives_the_planner_killed_at_a_random_instant": "passed",
        "test_the_map_server_answers_through_a_random_schedule_of_faults": "passed",
        "test_the_planner_is_back_under_a_restart_policy": "passed",
        "test_the_rest_outlives_the_planner_killed_holding_a_lock": "passed",
        "test_the_navigator_serves_goals_only_while_active_and_outlives_the_planner": "passed",
        "test_the_planner_plans_on_what_odometry_still_arrives": "passed",
        "test_late_odometry_delays_the_plans_by_as_much": "passed",
    }
    # the seeded trials: each recorded with its seed, its fault and what
    # every watched topic did; the rate held
    seeded = next(s for s in run["scenarios"] if "random_instant" in s["nodeid"])
    assert len(seeded["trials"]) == 3 and len({t["seed"] for t in seeded["trials"]}) == 3
    for t in seeded["trials"]:
        assert t["outcome"] == "survived", t
        assert [(f["node"], f["kind"]) for f in t["details"]["faults"]] == [("/planner", "SIGKILL")]
        assert t["details"]["topics"]["/odom"]["rate_hz"] >= 9.0
        assert t["latency_ms"]["get_map"] < 500
    assert [e["met"] for e in seeded["expectations"]] == [True, True]
    assert seeded["profile"] == "shared" and seeded["fault"] == "planner SIGKILL at a random instant"
    # a message fault is each trial's history too, filed under its topic
    lossy = next(s for s in run["scenarios"] if "still_arrives" in s["nodeid"])
    for t in lossy["trials"]:
        assert [(f["node"], f["kind"]) for f in t["details"]["faults"]] == [("/odom", "drop")], t
    # the report names the user's project and the versions it ran on
    assert run["run"]["project"] == "demo-robot"
    packages = run["run"]["packages"]
    assert {"demo-robot", "cloneguard", "ros-jazzy-rclpy", "ros-fastrtps"} <= set(packages), packages
    assert packages["demo-robot"] == "0.1.0"
    # a schedule's faults are each trial's history, in the order they began
    scheduled = next(s for s in run["scenarios"] if "random_schedule" in s["nodeid"])
    for t in scheduled["trials"]:
        faults = [(f["node"], f["kind"]) for f in t["details"]["faults"]]
        assert len(faults) == 3 and sum(node == "/odometry" for node, _ in faults) == 2, faults
        assert ("/planner", "SIGSEGV") in faults
        starts = [f["from_ms"] for f in t["details"]["faults"]]
        assert starts == sorted(starts)


def test_the_example_uses_only_the_public_test_api():
    public = {
        "cloneguard.harness.system",
        "cloneguard.harness.schedule",
        "cloneguard.harness.composition",
        "cloneguard.harness.named_faults",
        "cloneguard.harness.system_trials",  # Measure
    }
    for path in DEMO.rglob("*.py"):
        for line in path.read_text().splitlines():
            if line.startswith(("from cloneguard", "import cloneguard")):
                module = line.split()[1]
                assert module in public, f"{path.relative_to(REPO)} imports {module}"
