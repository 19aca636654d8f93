"""The container's services behave like rclcpp_components' ComponentManager."""

import time

import pytest
from std_msgs.msg import String

PKG = "cloneguard"
TALKER = "cloneguard::Talker"
LISTENER = "cloneguard::Listener"

MODES = [
    pytest.param([], id="single-threaded"),
    pytest.param(["--use_multi_threaded_executor"], id="multi-threaded"),
]


@pytest.mark.parametrize("container_args", MODES)
def test_ids_start_at_one_and_are_never_reused(client):
    assert client.load_ok(PKG, TALKER).unique_id == 1
    assert client.load_ok(PKG, LISTENER).unique_id == 2
    assert client.unload(1).success
    third = client.load_ok(PKG, TALKER)
    assert third.unique_id == 3
    assert client.list() == [(2, "/listener"), (3, "/talker")]


def test_a_failed_load_answers_zero_and_empty_name(client):
    resp = client.load(PKG, "cloneguard::NoSuchThing")
    assert (resp.success, resp.unique_id, resp.full_node_name) == (False, 0, "")


def test_a_constructor_failure_uses_up_its_id_like_upstream(client):
    # The id is taken once the class is found; a throwing constructor spends it.
    failed = client.load(PKG, TALKER, parameters={"period": -1.0})
    assert not failed.success
    assert "Component constructor threw an exception" in failed.error_message
    assert "period" in failed.error_message
    assert client.load_ok(PKG, TALKER).unique_id == 2


def test_lookup_failures_do_not_use_up_ids(client):
    assert not client.load("no_such_package", TALKER).success
    assert not client.load(PKG, "cloneguard::NoSuchThing").success
    assert client.load_ok(PKG, TALKER).unique_id == 1


def test_upstream_error_texts(client):
    assert client.load("no_such_package", TALKER).error_message == ("Could not find requested resource in ament index")
    assert client.load(PKG, "cloneguard::NoSuchThing").error_message == (
        "Failed to find class with the requested plugin name."
    )
    assert client.unload(42).error_message == "No node found with unique_id: 42"


def test_unload_twice(client):
    uid = client.load_ok(PKG, TALKER).unique_id
    first = client.unload(uid)
    second = client.unload(uid)
    assert first.success and first.error_message == ""
    assert not second.success
    assert second.error_message == f"No node found with unique_id: {uid}"
    assert client.list() == []


@pytest.mark.parametrize(
    "name, namespace, expected",
    [
        ("", "", "/talker"),
        ("my_talker", "", "/my_talker"),
        ("", "/robot", "/robot/talker"),
        ("front", "/robot/arm", "/robot/arm/front"),
    ],
)
def test_node_name_and_namespace_overrides(client, name, namespace, expected):
    resp = client.load_ok(PKG, TALKER, node_name=name, node_namespace=namespace)
    assert resp.full_node_name == expected
    assert client.list() == [(resp.unique_id, expected)]


@pytest.mark.parametrize("container_args", MODES)
def test_remap_rules_and_parameters_reach_the_node(client):
    heard = client.subscribe(String, "/renamed_topic")
    client.load_ok(
        PKG,
        TALKER,
        remap_rules=["chatter:=renamed_topic"],
        parameters={"message": "bonjour", "period": 0.02},
    )
    msg = heard.wait_for(lambda m: True, timeout=10, what="remapped talker output")
    assert msg.data.startswith("bonjour ")


def test_nodes_talk_to_each_other_inside_the_container(client):
    from std_msgs.msg import UInt64

    counts = client.subscribe(UInt64, "/listener/received")
    client.load_ok(PKG, TALKER, parameters={"period": 0.02})
    client.load_ok(PKG, LISTENER)
    counts.wait_for(lambda m: m.data >= 5, timeout=10, what="listener count >= 5")


def test_extra_arguments_use_intra_process_comms_is_accepted(client):
    resp = client.load_ok(PKG, TALKER, extra_arguments={"use_intra_process_comms": True})
    assert resp.unique_id == 1


def test_renamed_and_namespaced_container(container_factory):
    proc = container_factory.start(["--ros-args", "-r", "__node:=my_container", "-r", "__ns:=/robot"])
    cli = container_factory.connect(proc, "/robot/my_container")
    assert cli.load_ok(PKG, TALKER).full_node_name == "/talker"
    services = {name for name, _types in cli.node.get_service_names_and_types()}
    assert "/robot/my_container/_container/list_nodes" in services
    assert not any(name.startswith("/ComponentManager/") for name in services)


@pytest.mark.parametrize("container_args", [[], ["--isolated", "--profile", "shared"]], ids=["threads", "shared"])
def test_an_unloaded_node_takes_its_type_description_service_with_it(client):
    # Nodes that share the container's Context: rclpy alone would leave the
    # service's DDS endpoints behind (container/construction.py).
    service = "/tds/get_type_description"

    def offered():
        return any(name == service for name, _ in client.node.get_service_names_and_types())

    uid = client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name="tds").unique_id
    deadline = time.monotonic() + 10
    while not offered():
        assert time.monotonic() < deadline, f"{service} never appeared"
        time.sleep(0.1)
    assert client.unload(uid).success
    deadline = time.monotonic() + 10
    while offered():
        assert time.monotonic() < deadline, f"{service} is still offered after the unload"
        time.sleep(0.1)
