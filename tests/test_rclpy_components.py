"""Components registered for rclpy's composition proposal (entry-point group
``rclpy_components``, ros2/rclpy PR #599) load unchanged."""

import pytest


@pytest.fixture
def container_env(misfit_env):
    return misfit_env


@pytest.mark.parametrize("container_args", [[], ["--isolated"]], ids=["threads", "isolated"])
def test_a_component_registered_only_for_rclpy_components_loads(client):
    resp = client.load_ok("misfit_components", "misfits::RclpyStyle", node_name="proposal")
    assert resp.full_node_name == "/proposal"
    assert client.list() == [(resp.unique_id, "/proposal")]
    # The same rules as our own group: only installed names.
    resp = client.load("misfit_components", "misfits::NotRegistered")
    assert (resp.success, resp.error_message) == (False, "Failed to find class with the requested plugin name.")
