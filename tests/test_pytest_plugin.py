"""The harness's pytest plugin changes nothing for a test that uses none of
its fixtures, and sets up the ROS environment of those that do, for their
duration only. Each case is a pytest run of its own in a fresh process (the
environment of a process's first rclpy import is what counts)."""

import os
import subprocess
import sys
import textwrap

USER_ENV = {
    "RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp",  # not installed here: rcl exits 102 if rclpy is imported
    "FASTRTPS_DEFAULT_PROFILES_FILE": "/users/own/profile.xml",
    "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
}

TESTS = textwrap.dedent("""
    import os

    USER_ENV = {user_env!r}

    def test_plain_first():
        assert {{k: os.environ.get(k) for k in USER_ENV}} == USER_ENV

    def test_with_a_container(client):
        assert client.list() == []
        assert os.environ["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
        assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"].endswith("fastdds_no_shm.xml")
        assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in os.environ

    def test_plain_after():
        assert {{k: os.environ.get(k) for k in USER_ENV}} == USER_ENV
""")


def _run(tmp_path, *select):
    (tmp_path / "test_user.py").write_text(TESTS.format(user_env=USER_ENV))
    env = {**os.environ, **USER_ENV}
    return subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", "-p", "no:cacheprovider", "test_user.py", *select],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_run_that_uses_no_fixture_keeps_the_users_ros_environment(tmp_path):
    proc = _run(tmp_path, "-k", "plain")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "2 passed" in proc.stdout


def test_the_container_fixtures_set_the_ros_environment_for_their_test_only(tmp_path):
    proc = _run(tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "3 passed" in proc.stdout


MARKED = textwrap.dedent("""
    import pytest

    @pytest.mark.fault("SIGKILL")
    @pytest.mark.node("/planner")
    def test_planner_killed():
        pass

    @pytest.mark.fault("freeze", "SIGKILL")
    @pytest.mark.node("/odometry")
    def test_odometry_frozen_and_killed():
        pass

    def test_unmarked():
        pass
""")


def _selected(tmp_path, *options) -> list[str]:
    (tmp_path / "test_marked.py").write_text(MARKED)
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "--collect-only", "-W", "error::pytest.PytestUnknownMarkWarning",
         "-p", "no:cacheprovider", "test_marked.py", *options],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert proc.returncode in (0, 5), proc.stdout + proc.stderr  # 5: every test deselected
    return sorted(line.split("::")[1] for line in proc.stdout.splitlines() if "::" in line)


def test_fault_and_node_markers_pick_the_scenarios_a_ci_job_runs(tmp_path):
    everything = ["test_odometry_frozen_and_killed", "test_planner_killed", "test_unmarked"]
    assert _selected(tmp_path) == everything  # the markers are known: no warning, nothing dropped
    assert _selected(tmp_path, "--fault", "SIGKILL") == everything[:2]
    assert _selected(tmp_path, "--fault", "freeze") == ["test_odometry_frozen_and_killed"]
    assert _selected(tmp_path, "--fault", "SIGKILL", "--node", "/planner") == ["test_planner_killed"]
    assert _selected(tmp_path, "--node", "/planner", "--node", "/odometry") == everything[:2]
    assert _selected(tmp_path, "--fault", "SIGSEGV") == []
