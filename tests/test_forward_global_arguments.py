"""LoadNode's extra argument forward_global_arguments, as rclcpp_components
handles it: false (the default) builds the node without the container's
global ROS arguments, true with them (and a warning); not a boolean: refused."""

import pytest
from std_msgs.msg import String

from cloneguard.container.options import FORWARD_GLOBAL_WARNING

GLOBAL_REMAP = ["--ros-args", "-r", "chatter:=global_chatter"]
MODES = {
    "threads": [],
    "per-node": ["--isolated", "--profile", "per-node"],
    "shared": ["--isolated", "--profile", "shared"],
}


@pytest.mark.parametrize("container_args", [args + GLOBAL_REMAP for args in MODES.values()], ids=list(MODES))
def test_a_node_sees_the_containers_global_arguments_only_when_asked(client, container):
    plain = client.subscribe(String, "/chatter")
    remapped = client.subscribe(String, "/global_chatter")
    client.load_ok("cloneguard", "cloneguard::Talker", node_name="own", parameters={"period": 0.02})
    plain.wait_count(3, timeout=10)
    assert "forward_global_arguments" not in container.log_text()
    client.load_ok(
        "cloneguard",
        "cloneguard::Talker",
        node_name="forwarded",
        parameters={"period": 0.02},
        extra_arguments={"forward_global_arguments": True},
    )
    remapped.wait_count(3, timeout=10)
    assert FORWARD_GLOBAL_WARNING in container.log_text()


def test_forward_global_arguments_must_be_a_boolean(client):
    resp = client.load("cloneguard", "cloneguard::Talker", extra_arguments={"forward_global_arguments": "yes"})
    assert (resp.success, resp.error_message) == (
        False,
        "Extra component argument 'forward_global_arguments' must be a boolean",
    )
    assert client.list() == []
