"""Every malformed LoadNode gets success=false with a clear message, changes
nothing, and the container goes on serving."""

import re
import time
from importlib.metadata import entry_points

import pytest
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterValue

from cloneguard.container import spelling

PKG = "cloneguard"
TALKER = "cloneguard::Talker"


@pytest.fixture
def container_env(misfit_env):
    return misfit_env


def _param(name, type_):
    return ParameterMsg(name=name, value=ParameterValue(type=type_))


BAD_REQUESTS = [
    pytest.param(dict(package_name="", plugin_name=TALKER), "Could not find requested resource", id="empty-package"),
    pytest.param(dict(package_name=PKG, plugin_name=""), "Failed to find class", id="empty-plugin"),
    pytest.param(
        dict(package_name="nope", plugin_name=TALKER), "Could not find requested resource", id="unknown-package"
    ),
    pytest.param(dict(package_name=PKG, plugin_name="cloneguard::Nope"), "Failed to find class", id="unknown-plugin"),
    pytest.param(
        dict(package_name=PKG, plugin_name="cloneguard.container.components.talker:Talker"),
        "Failed to find class",
        id="module-path-is-not-a-plugin",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, node_name="bad name"),
        "Couldn't parse remap rule: '-r __node:=bad name'",
        id="invalid-node-name",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, node_name="9lives"),
        "Couldn't parse remap rule: '-r __node:=9lives'",
        id="node-name-starts-with-digit",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, node_namespace="/a//b"),
        "Couldn't parse remap rule: '-r __ns:=/a//b'",
        id="invalid-namespace",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, node_namespace="relative"),
        "Couldn't parse remap rule: '-r __ns:=relative'",
        id="relative-namespace",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, remap_rules=["nocolon"]),
        "Couldn't parse remap rule: '-r nocolon'",
        id="remap-without-separator",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, remap_rules=["a:=b c"]),
        "Couldn't parse remap rule: '-r a:=b c'",
        id="remap-with-space",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, remap_rules=["a:=b", ":=x"]),
        "Couldn't parse remap rule: '-r :=x'",
        id="remap-empty-side",
    ),
    pytest.param(
        dict(package_name="CLONEGUARD", plugin_name=TALKER), "Could not find requested resource", id="package-name-case"
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, parameters=[_param("period", 0)]),
        "Invalid parameter 'period': its value type is not set",
        id="parameter-not-set",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, parameters=[_param("period", 99)]),
        "Invalid parameter 'period'",
        id="parameter-unknown-type",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, parameters=[_param("", 2)]),
        "the name is empty",
        id="parameter-empty-name",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, parameters={"period": "fast"}),
        "expecting type 'DOUBLE'",
        id="parameter-wrong-type",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, extra_arguments={"use_intra_process_comms": "yes"}),
        "Extra component argument 'use_intra_process_comms' must be a boolean",
        id="extra-argument-type",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, extra_arguments={"cloneguard.profile": "per-process"}),
        "Extra component argument 'cloneguard.profile' must be one of per-node, shared, got 'per-process'",
        id="profile-unknown",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, extra_arguments={"cloneguard.profile": 1.0}),
        "Extra component argument 'cloneguard.profile' must be a string",
        id="profile-type",
    ),
    pytest.param(
        dict(package_name=PKG, plugin_name=TALKER, extra_arguments={"cloneguard.profile": "shared"}),
        "a participant profile (cloneguard.profile) needs an isolated container (--isolated)",
        id="profile-in-thread-mode",
    ),
    pytest.param(
        dict(package_name="misfit-components", plugin_name="misfits::Raises"),
        "sensor not found on /dev/imaginary",
        id="constructor-raises",
    ),
    pytest.param(
        dict(package_name="misfit-components", plugin_name="misfits::NotANode"),
        "is not a subclass of rclpy.node.Node",
        id="not-a-node",
    ),
    pytest.param(
        dict(package_name="misfit-components", plugin_name="misfits::IgnoresOptions"),
        "unexpected keyword argument",
        id="constructor-takes-no-options",
    ),
    pytest.param(
        dict(package_name="misfit-components", plugin_name="misfits::Missing"),
        "Failed to import component 'misfits::Missing'",
        id="plugin-module-missing",
    ),
    pytest.param(
        dict(package_name="misfit-components", plugin_name="misfits::DeclaresInteger", parameters={"count": "three"}),
        "expecting type 'INTEGER'",
        id="misfit-parameter-type",
    ),
]


@pytest.mark.parametrize("fields, message", BAD_REQUESTS)
def test_bad_load_is_refused_clearly_and_changes_nothing(client, fields, message):
    fields = dict(fields)
    package, plugin = fields.pop("package_name"), fields.pop("plugin_name")
    kept = client.load_ok(PKG, TALKER, node_name="kept")
    resp = client.load(package, plugin, **fields)
    assert not resp.success
    assert message in resp.error_message
    assert (resp.unique_id, resp.full_node_name) == (0, "")
    # Nothing changed, and the container still serves.
    assert client.list() == [(kept.unique_id, "/kept")]
    again = client.load_ok(PKG, TALKER, node_name="after")
    assert client.list() == [(kept.unique_id, "/kept"), (again.unique_id, "/after")]


def test_log_level_applies_to_the_node(client, container):
    client.load_ok("misfit-components", "misfits::DebugLogger", node_name="quiet")
    client.load_ok("misfit-components", "misfits::DebugLogger", node_name="chatty", log_level=10)
    deadline = time.monotonic() + 10
    while container.log_text().count("info line from a timer") < 2:
        assert time.monotonic() < deadline, "the nodes' timers never logged"
        time.sleep(0.05)
    # Each node logs its debug line before its info line, so both are in.
    debug_lines = [ln for ln in container.log_text().splitlines() if "debug line from a timer" in ln]
    assert len(debug_lines) == 1 and "[chatty]" in debug_lines[0]


def _plugins_of(distribution: str) -> set[str]:
    """The component names a distribution installs, read here, not by the container."""
    groups = ("cloneguard.components", "rclpy_components")
    return {ep.name for g in groups for ep in entry_points(group=g) if ep.dist and ep.dist.name == distribution}


# A misspelt name gets upstream's answer, word for word; only the container's
# log says what there is, the closest first.
MISSPELT = [
    pytest.param(PKG, "cloneguard::Talkr", "Failed to find class with the requested plugin name.", TALKER, id="plugin"),
    pytest.param("clonguard", TALKER, "Could not find requested resource in ament index", PKG, id="package"),
]


@pytest.mark.parametrize("package, plugin, answer, meant", MISSPELT)
def test_misspelt_name_is_answered_as_upstream_and_logged_with_the_closest(
    client, container, package, plugin, answer, meant
):
    resp = client.load(package, plugin)
    assert (resp.success, resp.error_message) == (False, answer)
    line = container.wait_for_log(rf"Failed to load component: {re.escape(answer)} \((.*)\)", timeout=10)
    offered = line.group(1).split("closest first: ", 1)[1].split(", ")
    assert offered[0] == meant, line.group(0)
    if meant == TALKER:  # all the package's plugins, as there are fewer than the cap
        assert sorted(offered) == sorted(_plugins_of(PKG)), line.group(0)
    # The container goes on serving.
    again = client.load_ok(PKG, TALKER, node_name="after")
    assert client.list() == [(again.unique_id, "/after")]


def test_names_offered_are_capped_and_say_how_many_more():
    names = [f"pkg::Node{i}" for i in range(25)]
    listed = spelling.closest_listed("pkg::Nodee12", names, shown=10)
    first, more = listed.split(" (and ")
    assert first.split(", ")[0] == "pkg::Node12"
    assert len(first.split(", ")) == 10 and more == "15 more)"
    assert spelling.closest_listed("x", ["b", "a"]) == "a, b"  # no "more" when all are shown; ties by name


def test_closeness_ignores_case():
    assert spelling.closest_first("CLONEGUARD", ["cloneguard-testrig", "demo-robot", "cloneguard"])[0] == "cloneguard"
