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
