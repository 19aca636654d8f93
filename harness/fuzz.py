"""Hostile clients, as hypothesis strategies, and the model a container must match.

The strategies cover every field of LoadNode (package and plugin names, node
name and namespace, log level, remap rules, parameters of every type and of
no known type, extra arguments: the container's own and unknown ones),
UnloadNode ids (live, gone, never given, the uint64 edges) and ListNodes;
rclpy's built-in parameters (``BUILTIN_PARAMETERS``) with values of every
type.
A load is *valid* (it must succeed) or *hostile* (anything may be asked; it
must be answered and leave the model unchanged unless it succeeded).

The model is what ListNodes must say: the loads that succeeded minus the
unloads that succeeded. ``Model.apply_*`` checks each answer against it:
an id is never reused (and ids only grow, as upstream's counter), a
failure says why, an unload of a live id succeeds and of any other id fails.
tests/test_request_fuzz.py drives real containers with these.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from composition_interfaces.srv import LoadNode
from hypothesis import strategies as st
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue

if TYPE_CHECKING:
    from composition_interfaces.srv import UnloadNode

PKG = "cloneguard"
#: components a valid load may name, with the parameters it may set
VALID_PLUGINS = ("cloneguard::Heartbeat", "cloneguard::Talker", "cloneguard::Listener", "cloneguard::EchoService")
UINT64_MAX = 2**64 - 1

# -- text --------------------------------------------------------------------

_NAME_START = "abcdefghijklmnopqrstuvwxyz"
_NAME_REST = _NAME_START + "0123456789_"
#: names rcl accepts: a letter, then letters, digits, single underscores
valid_names = st.builds(lambda a, b: a + b, st.sampled_from(_NAME_START), st.text(_NAME_REST, max_size=12)).filter(
    lambda s: "__" not in s and not s.endswith("_")
)
valid_namespaces = st.one_of(
    st.just(""), st.just("/"), st.lists(valid_names, min_size=1, max_size=3).map(lambda parts: "/" + "/".join(parts))
)

#: what a careless or hostile client puts in a string field
hostile_text = st.one_of(
    st.text(max_size=40),
    st.text(st.characters(codec="utf-8"), min_size=200, max_size=3000),
    st.sampled_from(
        [
            "",
            " ",
            "/",
            "//",
            "~",
            "~/x",
            "../../etc/passwd",
            "/tmp/x.so",
            "a::b::c",
            "::",
            "x:=y",
            "\x1b[31mred\x1b[0m",
            "nul\x00byte",
            "new\nline",
            "__node",
            "__ns",
            "{x}",
            "%s%n",
            "rclpy",
            "os.system('id')",
            "__import__('os')",
            "cloneguard::",
            "CLONEGUARD",
            "cloneguard ",
            "cloneguard::heartbeat",
            "cloneguard::Heartbeat\n",
            "faults",
            "1" * 300,
        ]
    ),
)
hostile_remaps = st.lists(
    st.one_of(
        hostile_text,
        st.builds(lambda a, b: f"{a}:={b}", hostile_text, hostile_text),
        st.sampled_from(
            [
                "__node:=x",
                "__ns:=/y",
                "__ns:=rel",
                "__node:=",
                ":=",
                "a:=b:=c",
                "chatter:=/other",
                "__log_level:=debug",
                "__params:=/nonexistent.yaml",
            ]
        ),
    ),
    max_size=4,
)

# -- parameters --------------------------------------------------------------

_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0.0, -0.0, 1e-12, 5e-324, 1e300, -1.0, math.nan, math.inf, -math.inf]),
)
_ints = st.one_of(st.integers(-(2**63), 2**63 - 1), st.sampled_from([0, -1, 2**62, 2**63 - 1, -(2**63)]))


@st.composite
def parameter_values(draw: st.DrawFn) -> ParameterValue:
    """A ParameterValue of any type rcl_interfaces names, or of none (0, or
    a number it never defined), with every field drawn regardless of type."""
    value = ParameterValue()
    value.type = draw(st.one_of(st.integers(0, 9), st.integers(10, 255)))
    value.bool_value = draw(st.booleans())
    value.integer_value = draw(_ints)
    value.double_value = draw(_floats)
    value.string_value = draw(hostile_text)
    value.byte_array_value = [bytes([b]) for b in draw(st.binary(max_size=16))]
    value.bool_array_value = draw(st.lists(st.booleans(), max_size=4))
    value.integer_array_value = draw(st.lists(_ints, max_size=4))
    value.double_array_value = draw(st.lists(_floats, max_size=4))
    value.string_array_value = draw(st.lists(hostile_text, max_size=3))
    return value


_parameter_names = st.one_of(
    st.sampled_from(
        [
            "period",
            "topic",
            "message",
            "limit",
            "use_sim_time",
            "qos_overrides./x.publisher.depth",
            "use_intra_process_comms",
            "cloneguard.cpu_quota",
            "cloneguard.fault.drop_loaded_event",
            "forward_global_arguments",
            "cloneguard.unknown",
            "",
        ]
    ),
    hostile_text,
)
#: rclpy's own parameters, which ``Node.__init__`` (or a publisher made with
#: QoS overriding options: Heartbeat's, topic ``~/heartbeat``) declares with
#: a type and checks before the component's own code runs
BUILTIN_PARAMETERS = (
    "use_sim_time",
    "start_type_description_service",
    *(
        f"qos_overrides.{topic}.publisher.{policy}"
        for topic in ("/heartbeat/heartbeat", "/chatter")
        for policy in ("history", "depth", "reliability", "durability")
    ),
)
#: every ParameterType value, each drawn for each built-in parameter
_PARAMETER_TYPES = st.sampled_from(range(ParameterType.PARAMETER_NOT_SET, ParameterType.PARAMETER_STRING_ARRAY + 1))


@st.composite
def builtin_parameters(draw: st.DrawFn) -> ParameterMsg:
    """A built-in parameter with a value of any type (most of them wrong)."""
    value = draw(parameter_values())
    value.type = draw(_PARAMETER_TYPES)
    return ParameterMsg(name=draw(st.sampled_from(BUILTIN_PARAMETERS)), value=value)


hostile_parameters = st.lists(
    st.one_of(
        st.builds(lambda n, v: ParameterMsg(name=n, value=v), _parameter_names, parameter_values()),
        builtin_parameters(),
    ),
    max_size=4,
)


def _double(name: str, value: float) -> ParameterMsg:
    return ParameterMsg(name=name, value=ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value))


def _bool(name: str, value: bool) -> ParameterMsg:
    return ParameterMsg(name=name, value=ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value))


# -- requests ----------------------------------------------------------------


@dataclass
class Load:
    request: LoadNode.Request
    valid: bool

    def __repr__(self) -> str:  # what a failing example prints: every field that is set
        r = self.request
        fields = {
            k: getattr(r, k)
            for k in ("package_name", "plugin_name", "node_name", "node_namespace", "log_level", "remap_rules")
        }
        fields["parameters"] = [(p.name, p.value.type) for p in r.parameters]
        fields["extra_arguments"] = [(p.name, p.value.type) for p in r.extra_arguments]
        return f"Load(valid={self.valid}, {fields!r})"


def _request(
    package: str,
    plugin: str,
    name: str,
    namespace: str,
    log_level: int,
    remaps: Iterable[str],
    parameters: Iterable[ParameterMsg],
    extra: Iterable[ParameterMsg],
) -> LoadNode.Request:
    req = LoadNode.Request()
    req.package_name, req.plugin_name = package, plugin
    req.node_name, req.node_namespace = name, namespace
    req.log_level = log_level
    req.remap_rules = list(remaps)
    req.parameters = list(parameters)
    req.extra_arguments = list(extra)
    return req


@st.composite
def valid_loads(draw: st.DrawFn, *, cgroups: bool) -> Load:
    """A load that must succeed: a demo component, a legal name, legal
    parameters and extra arguments."""
    plugin = draw(st.sampled_from(VALID_PLUGINS))
    params = []
    if plugin in ("cloneguard::Heartbeat", "cloneguard::Talker") and draw(st.booleans()):
        params.append(_double("period", draw(st.floats(0.01, 10.0))))
    extra = []
    if draw(st.booleans()):
        extra.append(_bool("use_intra_process_comms", draw(st.booleans())))
    if cgroups and draw(st.booleans()):
        extra.append(_double("cloneguard.cpu_quota", draw(st.floats(0.01, 4.0))))
    req = _request(
        PKG,
        plugin,
        draw(st.one_of(st.just(""), valid_names)),
        draw(valid_namespaces),
        draw(st.sampled_from([0, 10, 20, 30, 40, 50])),
        [],
        params,
        extra,
    )
    return Load(req, valid=True)


@st.composite
def hostile_loads(draw: st.DrawFn) -> Load:
    """Anything at all in any field; some fields kept plausible so that the
    request gets past the early checks to the later ones."""
    plausible = st.sampled_from([PKG])
    package = draw(st.one_of(plausible, hostile_text))
    plugin = draw(st.one_of(st.sampled_from(VALID_PLUGINS), hostile_text))
    name = draw(st.one_of(st.just(""), valid_names, hostile_text))
    namespace = draw(st.one_of(valid_namespaces, hostile_text))
    extra = draw(
        st.lists(
            st.one_of(
                st.builds(_double, st.just("cloneguard.cpu_quota"), _floats),
                st.builds(_bool, st.just("use_intra_process_comms"), st.booleans()),
                st.builds(lambda n, v: ParameterMsg(name=n, value=v), _parameter_names, parameter_values()),
            ),
            max_size=3,
        )
    )
    req = _request(
        package,
        plugin,
        name,
        namespace,
        draw(st.integers(0, 255)),
        draw(hostile_remaps),
        draw(hostile_parameters),
        extra,
    )
    return Load(req, valid=False)


@st.composite
def hostile_parameter_loads(draw: st.DrawFn) -> Load:
    """A load that gets past every early check to the constructor (a demo
    component, a legal name, no remap rules), with hostile parameters and
    at least one built-in one: what Node.__init__ and the component refuse
    part-way through building the node."""
    params = draw(hostile_parameters) + [draw(builtin_parameters())]
    req = _request(
        PKG,
        draw(st.sampled_from(VALID_PLUGINS)),
        draw(st.one_of(st.just(""), valid_names)),
        draw(st.sampled_from(["", "/"])),
        0,
        [],
        draw(st.permutations(params)),
        [],
    )
    return Load(req, valid=False)


def unload_ids(live: list[int], gone: list[int]) -> st.SearchStrategy[int]:
    """Ids to unload: live ones, unloaded ones, never-given ones, uint64 edges."""
    choices = [st.integers(0, UINT64_MAX), st.sampled_from([0, 1, 2**63 - 1, 2**63, UINT64_MAX])]
    if live:
        choices.append(st.sampled_from(live))
    if gone:
        choices.append(st.sampled_from(gone))
    return st.one_of(*choices)


# -- the model ---------------------------------------------------------------


@dataclass
class Model:
    """What the container must say it holds, and every id it ever gave."""

    live: dict[int, str] = field(default_factory=dict)  # unique_id -> full node name
    given: set[int] = field(default_factory=set)
    gone: list[int] = field(default_factory=list)
    highest: int = 0
    requests: int = 0

    def apply_load(self, load: Load, resp: LoadNode.Response) -> None:
        self.requests += 1
        if load.valid:
            assert resp.success, f"a valid load failed: {resp.error_message!r} ({load!r})"
        if not resp.success:
            assert resp.error_message, f"a failed load says nothing ({load!r})"
            assert len(resp.error_message) <= 4096, f"a {len(resp.error_message)}-character error message"
            return
        uid = resp.unique_id
        assert uid not in self.given, f"unique_id {uid} given twice"
        assert uid > self.highest, f"unique_id {uid} after {self.highest}: ids must only grow"
        assert resp.full_node_name.startswith("/"), f"full_node_name {resp.full_node_name!r}"
        self.given.add(uid)
        self.highest = uid
        self.live[uid] = resp.full_node_name

    def apply_unload(self, uid: int, resp: UnloadNode.Response) -> None:
        self.requests += 1
        if uid in self.live:
            assert resp.success, f"unloading live unique_id {uid} failed: {resp.error_message!r}"
            del self.live[uid]
            self.gone.append(uid)
        else:
            assert not resp.success, f"unloading unique_id {uid}, which is not loaded, succeeded"
            assert resp.error_message, f"a failed unload of {uid} says nothing"

    def apply_unloads_at_once(self, uid: int, responses: list) -> None:
        """The same id unloaded by several clients at once: at most one
        succeeds, exactly one if it was live."""
        self.requests += len(responses)
        won = sum(1 for r in responses if r.success)
        if uid in self.live:
            assert won == 1, f"{won} of {len(responses)} concurrent unloads of live unique_id {uid} succeeded"
            del self.live[uid]
            self.gone.append(uid)
        else:
            assert won == 0, f"{won} unloads of unique_id {uid}, which is not loaded, succeeded"

    def listed(self) -> list[tuple[int, str]]:
        return sorted(self.live.items())

    def node_names(self) -> set[str]:
        return set(self.live.values())
