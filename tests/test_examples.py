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
    assert "3 passed" in proc.stdout
    run = json.loads((report / "report.json").read_text())
    outcomes = {s["nodeid"].split("::", 1)[1]: s["outcome"] for s in run["scenarios"]}
    assert outcomes == {
        "test_odometry_and_the_map_outlive_the_planner[SIGSEGV]": "passed",
        "test_odometry_and_the_map_outlive_the_planner[SIGKILL]": "passed",
        "test_the_planner_is_back_under_a_restart_policy": "passed",
    }


def test_the_example_uses_only_the_public_test_api():
    public = {"cloneguard.harness.system"}
    for path in DEMO.rglob("*.py"):
        for line in path.read_text().splitlines():
            if line.startswith(("from cloneguard", "import cloneguard")):
                module = line.split()[1]
                assert module in public, f"{path.relative_to(REPO)} imports {module}"
