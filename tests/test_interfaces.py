"""The interface packages built by scripts/build_interfaces.py.

* composition_interfaces must be hash-identical to ROS 2 Jazzy's: the RIHS01
  type hashes that rmw uses (and announces in discovery) are compared with
  values read from an upstream build.
* cloneguard_interfaces/msg/ComponentEvent must have the agreed constants and
  fields.
* One LoadNode request and one ComponentEvent message go through rclpy.

Run `python scripts/build_interfaces.py` first.
"""

from __future__ import annotations

import ctypes
import json
import os
import sys
import time
from pathlib import Path

import pytest

try:
    from cloneguard_interfaces.msg import ComponentEvent
    from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
except ImportError as exc:  # pragma: no cover - message for a missing build
    raise ImportError(
        f"{exc}: the interface packages are not installed in this venv; run `python scripts/build_interfaces.py` first"
    ) from exc

from rclpy.type_support import check_for_type_support
from ros_support import ros_nodes

# Upstream ROS 2 Jazzy type hashes of composition_interfaces.  Read from the
# generated type descriptions (share/composition_interfaces/srv/*.json,
# "type_hashes") of an upstream build of ros2/rcl_interfaces, branch jazzy at
# tag 2.0.2 (commit 003987ecb81a32802ab27dd6d325b8c6b8b813cc; the .srv files
# are unchanged up to 2.2.0), built with the same ros-jazzy wheels
# (rcl_interfaces 2.0.3, rosidl 4.6.6).  The service hashes also match the
# TYPE_HASH constants in generated headers of an official Jazzy build.
UPSTREAM_HASHES = {
    "LoadNode": {
        "service": "RIHS01_2e521ef6066fba6d7fc3a3b175d486709f01b4d738d9a59188858546fc8e5acd",
        "request": "RIHS01_7d3496175f54f92d652547e144c9b2a3b22afd604f84ed70adfcd1cfe35801b5",
        "response": "RIHS01_08cdf942efabec2448fd03c131f3627a33ed05376400612425f871feb87ca9fd",
        "event": "RIHS01_db276d4eb31443e4d30cfb4b0c01bcd22af27fc95be8e1ba2cc56d7772219cd2",
    },
    "UnloadNode": {
        "service": "RIHS01_dce562f83adc735ddcfe9dfb927b89293d4dd0fe2b8fc91e772fb83e970a43b0",
        "request": "RIHS01_95d5cfc357956740190c7685ac868d9c7c98dcb8c1416aae8eaa351422074e12",
        "response": "RIHS01_fa7fc38f9206220a6bc1558a3c019269e5aa592f7fae01dffbd19f56eb86d599",
        "event": "RIHS01_448a525df1406f0c3dc653b03c68cb80d5c67cff48a8006a65f76f13e23e29cf",
    },
    "ListNodes": {
        "service": "RIHS01_13f30d73a74c844ee4bacf78f3680f08777cad137f10fbd6a648544cc7b59d2a",
        "request": "RIHS01_57c879a1825b3fa15fd58e70d2e73223af6b9c45c7ae104cc107e73464d3a724",
        "response": "RIHS01_b7cd8401aedcd85c4cedce384944001d5c1ab611e0164a8207045cfcaf4a2584",
        "event": "RIHS01_843ad4c80092060d68dbf8008ce53354314d98257cddddaf55df03abd7321b38",
    },
}
SERVICES = {"LoadNode": LoadNode, "UnloadNode": UnloadNode, "ListNodes": ListNodes}

COMPONENT_EVENT_CONSTANTS = {"LOADED": 0, "UNLOADED": 1, "LOAD_FAILED": 2, "CRASHED": 3, "REPAIRED": 4}
COMPONENT_EVENT_FIELDS = {
    "stamp": "builtin_interfaces/Time",
    "event_type": "uint8",
    "unique_id": "uint64",
    "full_node_name": "string",
    "package_name": "string",
    "plugin_name": "string",
    "error_message": "string",
    "pid": "int32",
    "exit_signal": "int32",
    "exit_code": "int32",
    "start_time": "uint64",
    "allocator_quarantined": "boolean",
    "repaired_state": "string",
}

SHARE = Path(sys.prefix) / "share"


# --- reading the hash the way rmw does -------------------------------------
#
# A generated class's _TYPE_SUPPORT is a capsule around the
# rosidl_typesupport_c handle that rclpy hands to rcl/rmw.  rmw_fastrtps takes
# the type hash from its get_type_hash_func (and announces it in discovery),
# so calling that function reads exactly what goes on the wire.  The layouts
# are rosidl_runtime_c's (Jazzy) message_/service_type_support_struct.h.


class _TypeHash(ctypes.Structure):  # rosidl_type_hash_t
    _fields_ = [("version", ctypes.c_uint8), ("value", ctypes.c_uint8 * 32)]


_GetTypeHash = ctypes.CFUNCTYPE(ctypes.POINTER(_TypeHash), ctypes.c_void_p)


class _MessageTypeSupport(ctypes.Structure):  # rosidl_message_type_support_t
    _fields_ = [
        ("typesupport_identifier", ctypes.c_char_p),
        ("data", ctypes.c_void_p),
        ("func", ctypes.c_void_p),
        ("get_type_hash_func", _GetTypeHash),
        ("get_type_description_func", ctypes.c_void_p),
        ("get_type_description_sources_func", ctypes.c_void_p),
    ]


class _ServiceTypeSupport(ctypes.Structure):  # rosidl_service_type_support_t
    _fields_ = [
        ("typesupport_identifier", ctypes.c_char_p),
        ("data", ctypes.c_void_p),
        ("func", ctypes.c_void_p),
        ("request_typesupport", ctypes.c_void_p),
        ("response_typesupport", ctypes.c_void_p),
        ("event_typesupport", ctypes.c_void_p),
        ("event_message_create_handle_function", ctypes.c_void_p),
        ("event_message_destroy_handle_function", ctypes.c_void_p),
        ("get_type_hash_func", _GetTypeHash),
        ("get_type_description_func", ctypes.c_void_p),
        ("get_type_description_sources_func", ctypes.c_void_p),
    ]


_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype = ctypes.c_void_p
_capsule_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]


def _format(hash_ptr) -> str:
    h = hash_ptr.contents
    return f"RIHS{h.version:02d}_{bytes(h.value).hex()}"


def _handle(cls) -> int:
    check_for_type_support(cls)  # imports the typesupport extension
    address = _capsule_pointer(cls._TYPE_SUPPORT, None)
    assert address, f"{cls.__name__} has no type support handle"
    return address


def message_type_hash(address: int) -> str:
    ts = _MessageTypeSupport.from_address(address)
    assert ts.typesupport_identifier == b"rosidl_typesupport_c"
    return _format(ts.get_type_hash_func(address))


def service_type_hashes(srv) -> dict[str, str]:
    address = _handle(srv)
    ts = _ServiceTypeSupport.from_address(address)
    assert ts.typesupport_identifier == b"rosidl_typesupport_c"
    return {
        "service": _format(ts.get_type_hash_func(address)),
        "request": message_type_hash(ts.request_typesupport),
        "response": message_type_hash(ts.response_typesupport),
        "event": message_type_hash(ts.event_typesupport),
    }


def installed_json_hashes(package: str, kind: str, name: str) -> dict[str, str]:
    """type_name -> hash from the installed type description JSON."""
    data = json.loads((SHARE / package / kind / f"{name}.json").read_text())
    return {entry["type_name"]: entry["hash_string"] for entry in data["type_hashes"]}


# --- composition_interfaces -------------------------------------------------


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_type_support_hashes_equal_upstream_jazzy(name):
    assert service_type_hashes(SERVICES[name]) == UPSTREAM_HASHES[name]


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_request_and_response_classes_carry_the_same_hashes(name):
    srv = SERVICES[name]
    assert message_type_hash(_handle(srv.Request)) == UPSTREAM_HASHES[name]["request"]
    assert message_type_hash(_handle(srv.Response)) == UPSTREAM_HASHES[name]["response"]


@pytest.mark.parametrize("name", sorted(SERVICES))
def test_installed_type_description_agrees(name):
    hashes = installed_json_hashes("composition_interfaces", "srv", name)
    base = f"composition_interfaces/srv/{name}"
    assert hashes[base] == UPSTREAM_HASHES[name]["service"]
    assert hashes[f"{base}_Request"] == UPSTREAM_HASHES[name]["request"]
    assert hashes[f"{base}_Response"] == UPSTREAM_HASHES[name]["response"]
    assert hashes[f"{base}_Event"] == UPSTREAM_HASHES[name]["event"]


def test_load_node_fields():
    assert LoadNode.Request.get_fields_and_field_types() == {
        "package_name": "string",
        "plugin_name": "string",
        "node_name": "string",
        "node_namespace": "string",
        "log_level": "uint8",
        "remap_rules": "sequence<string>",
        "parameters": "sequence<rcl_interfaces/Parameter>",
        "extra_arguments": "sequence<rcl_interfaces/Parameter>",
    }
    assert LoadNode.Response.get_fields_and_field_types() == {
        "success": "boolean",
        "error_message": "string",
        "full_node_name": "string",
        "unique_id": "uint64",
    }


# --- cloneguard_interfaces ----------------------------------------------------


def test_component_event_constants():
    for name, value in COMPONENT_EVENT_CONSTANTS.items():
        assert getattr(ComponentEvent, name) == value
        assert getattr(ComponentEvent(), name) == value
    # The generated metaclass lists every constant in __prepare__.
    assert type(ComponentEvent).__prepare__("ComponentEvent", ()) == COMPONENT_EVENT_CONSTANTS


def test_component_event_constant_types():
    from rosidl_parser.definition import IdlLocator, Message
    from rosidl_parser.parser import parse_idl_file

    idl = parse_idl_file(IdlLocator(SHARE / "cloneguard_interfaces", "msg/ComponentEvent.idl"))
    (message,) = idl.content.get_elements_of_type(Message)
    assert [(c.name, c.type.typename, c.value) for c in message.constants] == [
        (name, "uint8", value) for name, value in COMPONENT_EVENT_CONSTANTS.items()
    ]


def test_component_event_fields():
    assert ComponentEvent.get_fields_and_field_types() == COMPONENT_EVENT_FIELDS


def test_component_event_serialization_round_trip():
    """Extreme values of each integer field survive CDR serialization."""
    from builtin_interfaces.msg import Time
    from rclpy.serialization import deserialize_message, serialize_message

    msg = ComponentEvent(
        stamp=Time(sec=1, nanosec=2),
        event_type=255,
        unique_id=2**64 - 1,
        full_node_name="/ns/talker",
        package_name="cloneguard",
        plugin_name="cloneguard::Talker",
        error_message="killed by SIGSEGV",
        pid=-(2**31),
        exit_signal=2**31 - 1,
        exit_code=-1,
        start_time=2**64 - 1,
        allocator_quarantined=True,
        repaired_state="progress-board",
    )
    back = deserialize_message(serialize_message(msg), ComponentEvent)
    assert back == msg
    assert back.pid == -(2**31) and back.exit_code == -1 and back.start_time == 2**64 - 1


def test_component_event_hash_consistent():
    hashes = installed_json_hashes("cloneguard_interfaces", "msg", "ComponentEvent")
    assert message_type_hash(_handle(ComponentEvent)) == hashes["cloneguard_interfaces/msg/ComponentEvent"]


# --- through rclpy and Fast DDS -------------------------------------------------


@pytest.fixture(scope="module")
def ros():
    with ros_nodes("cloneguard_interfaces_test") as ((node,), executor):
        yield node, executor


def _endpoints(node, topic):
    return node.get_publishers_info_by_topic(topic, no_mangle=True) + node.get_subscriptions_info_by_topic(
        topic, no_mangle=True
    )


def test_discovery_announces_upstream_hashes(ros):
    """rmw_fastrtps puts the request/response hashes in each endpoint's
    discovery data; read them back from the ROS graph."""
    node, _ = ros
    services, clients = [], []
    for name, srv in SERVICES.items():
        service_name = f"hash_check/{name.lower()}"
        services.append(node.create_service(srv, service_name, lambda req, resp: resp))
        clients.append(node.create_client(srv, service_name))
    try:
        for name in SERVICES:
            base = f"hash_check/{name.lower()}"
            topics = {
                f"rq/{base}Request": UPSTREAM_HASHES[name]["request"],
                f"rr/{base}Reply": UPSTREAM_HASHES[name]["response"],
            }
            for topic, expected in topics.items():
                deadline = time.monotonic() + 10
                infos = _endpoints(node, topic)
                while len(infos) < 2 and time.monotonic() < deadline:
                    time.sleep(0.05)
                    infos = _endpoints(node, topic)
                assert len(infos) >= 2, f"no endpoints seen for {topic}"
                assert {str(info.topic_type_hash) for info in infos} == {expected}, topic
    finally:
        for client in clients:
            node.destroy_client(client)
        for service in services:
            node.destroy_service(service)


def test_load_node_round_trip(ros):
    node, executor = ros
    seen = []

    def handle(request, response):
        seen.append(request)
        response.success = True
        response.full_node_name = f"{request.node_namespace.rstrip('/')}/{request.node_name}"
        response.unique_id = 42
        return response

    service = node.create_service(LoadNode, "smoke/load_node", handle)
    client = node.create_client(LoadNode, "smoke/load_node")
    try:
        assert client.wait_for_service(timeout_sec=10.0), "LoadNode service never appeared"
        from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue

        request = LoadNode.Request(
            package_name="cloneguard",
            plugin_name="cloneguard::Talker",
            node_name="talker",
            node_namespace="/smoke",
            log_level=20,
            remap_rules=["chatter:=talk"],
            parameters=[
                Parameter(name="rate", value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=5.0))
            ],
        )
        future = client.call_async(request)
        executor.spin_until_future_complete(future, timeout_sec=10.0)
        assert future.done(), "no LoadNode response within 10 s"
        response = future.result()
        assert response.success and response.unique_id == 42
        assert response.full_node_name == "/smoke/talker"
        assert seen[0].remap_rules == ["chatter:=talk"]
        assert seen[0].parameters[0].value.double_value == 5.0
    finally:
        node.destroy_client(client)
        node.destroy_service(service)


def test_component_event_pub_sub(ros):
    node, executor = ros
    received: list[ComponentEvent] = []
    subscription = node.create_subscription(ComponentEvent, "smoke/component_events", received.append, 10)
    publisher = node.create_publisher(ComponentEvent, "smoke/component_events", 10)
    try:
        sent = ComponentEvent(
            event_type=ComponentEvent.LOAD_FAILED,
            unique_id=7,
            full_node_name="/smoke/talker",
            package_name="cloneguard",
            plugin_name="cloneguard::Talker",
            error_message="no such plugin",
            pid=os.getpid(),
            exit_signal=0,
            exit_code=1,
            start_time=time.time_ns(),
        )
        sent.stamp = node.get_clock().now().to_msg()
        deadline = time.monotonic() + 10
        while not received and time.monotonic() < deadline:
            publisher.publish(sent)
            executor.spin_once(timeout_sec=0.1)
        assert received, "no ComponentEvent received within 10 s"
        assert received[0] == sent
        infos = node.get_publishers_info_by_topic("/smoke/component_events")
        expected = installed_json_hashes("cloneguard_interfaces", "msg", "ComponentEvent")
        assert {str(i.topic_type_hash) for i in infos} == {expected["cloneguard_interfaces/msg/ComponentEvent"]}
    finally:
        node.destroy_publisher(publisher)
        node.destroy_subscription(subscription)
