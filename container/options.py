"""Turn a LoadNode request into the arguments a component's Node is built with.

Everything here is validation and translation; nothing is constructed. A bad
parameter or extra argument raises :class:`LoadError` with a message that
says what is wrong, and the manager answers ``success=false`` with it before
it takes a unique id, as rclcpp_components does. The node name, namespace
and remap rules are, as there, handed to the node's constructor as ROS
arguments (rules first, then ``__node:=``, then ``__ns:=``: the first rule
that matches wins) and judged by rcl when the node is built: a bad one fails
the load after an id was taken, with rcl's message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from rclpy.parameter import Parameter

from . import seams
from .isolated.profiles import PROFILES
from .memory_budget import MEMORY_LIMIT, OOM_SCORE_ADJ, OOM_SCORE_ADJ_RANGE, parse_size

if TYPE_CHECKING:
    from collections.abc import Iterable

    from composition_interfaces.srv import LoadNode
    from rcl_interfaces.msg import Parameter as ParameterMsg
    from rclpy.context import Context

# rcutils log severities a LoadNode.log_level may set (0 means "unset"); like
# rclcpp_components, any other value is ignored.
LOG_LEVELS = {10: "debug", 20: "info", 30: "warn", 40: "error", 50: "fatal"}
# The CPU quota a node may ask for, in CPUs (cgroup cpu.max / cfs_quota_us).
CPU_QUOTA_RANGE = (0.001, 1024.0)

# extra_arguments this container understands, and the type each must have.
# CPU_QUOTA (CPUs, e.g. 0.5) puts an isolated node in a cgroup with that quota.
# seams.DROP_LOADED_EVENT (the node loads, its LOADED event is not sent) is
# fault injection: known only where the test rig is installed.
CPU_QUOTA = "cloneguard.cpu_quota"
# PROFILE ("per-node" or "shared") builds this one node of an isolated
# container in that participant profile, whatever the container's --profile.
PROFILE = "cloneguard.profile"
KNOWN_EXTRA_ARGUMENTS = {
    "use_intra_process_comms": Parameter.Type.BOOL,
    # As rclcpp_components: false (its default) builds the node without the
    # container's global ROS arguments, true with them.
    "forward_global_arguments": Parameter.Type.BOOL,
    CPU_QUOTA: Parameter.Type.DOUBLE,
    PROFILE: Parameter.Type.STRING,
    # MEMORY_LIMIT (memory_budget.py): this node's memory budget, bytes or
    # a size text ("512M"); either type.
    MEMORY_LIMIT: (Parameter.Type.INTEGER, Parameter.Type.STRING),
    # OOM_SCORE_ADJ: how the container's memory watch weighs this node.
    OOM_SCORE_ADJ: Parameter.Type.INTEGER,
}
# rclcpp_components' warning when forward_global_arguments is true, word for word.
FORWARD_GLOBAL_WARNING = (
    "forward_global_arguments is true by default in nodes, but is not recommended in a component "
    "manager. If true, this will cause this node's behavior to be influenced by global arguments, "
    "not only those targeted at this node."
)
FAULT_EXTRA_ARGUMENTS = {seams.DROP_LOADED_EVENT: Parameter.Type.BOOL}
_TYPE_NAMES = {
    Parameter.Type.BOOL: "a boolean",
    Parameter.Type.DOUBLE: "a double",
    Parameter.Type.STRING: "a string",
    Parameter.Type.INTEGER: "an integer",
}


class LoadError(Exception):
    """A LoadNode request that cannot be honoured; str() is the answer's text.
    ``log_detail``, when there is one, goes to the container's log after it
    and never to the client (say, what a misspelt name may have meant)."""

    def __init__(self, message: str, log_detail: str = ""):
        super().__init__(message)
        self.log_detail = log_detail


@dataclass(frozen=True)
class NodeArguments:
    """What a component's constructor receives, already validated."""

    cli_args: list[str]
    parameter_overrides: list[Parameter]
    use_intra_process_comms: bool = False
    forward_global_arguments: bool = False
    drop_loaded_event: bool = False
    cpu_quota: float | None = None
    memory_limit: int | None = None  # MEMORY_LIMIT, bytes (0: none): None, the container's
    oom_score_adj: int | None = None  # OOM_SCORE_ADJ: None, 0
    profile: str | None = None  # PROFILE: None, the container's
    requested_name: str = ""  # /namespace/name when the request names the node, else ""
    plugin: str = ""  # the request's plugin_name
    log_level: int = 0
    extra: dict[str, object] = field(default_factory=dict)

    def node_kwargs(self, context: Context) -> dict:
        """Keyword arguments for ``rclpy.node.Node.__init__``."""
        return {
            "context": context,
            "cli_args": list(self.cli_args),
            "use_global_arguments": self.forward_global_arguments,
            "parameter_overrides": list(self.parameter_overrides),
        }


def _parameters(messages: Iterable[ParameterMsg]) -> list[Parameter]:
    out = []
    for msg in messages:
        if not msg.name:
            raise LoadError("Invalid parameter: the name is empty")
        try:
            param = Parameter.from_parameter_msg(msg)
        except ValueError as exc:
            raise LoadError(f"Invalid parameter {msg.name!r}: {exc}") from None
        if param.type_ == Parameter.Type.NOT_SET:
            raise LoadError(f"Invalid parameter {msg.name!r}: its value type is not set")
        out.append(param)
    return out


def _extra_arguments(messages: Iterable[ParameterMsg]) -> dict[str, object]:
    extra = {}
    for param in _parameters(messages):
        wanted = KNOWN_EXTRA_ARGUMENTS.get(param.name)
        if wanted is None and seams.enabled():
            wanted = FAULT_EXTRA_ARGUMENTS.get(param.name)
        if wanted is not None and param.type_ not in (wanted if isinstance(wanted, tuple) else (wanted,)):
            kinds = " or ".join(_TYPE_NAMES[w] for w in (wanted if isinstance(wanted, tuple) else (wanted,)))
            raise LoadError(f"Extra component argument '{param.name}' must be {kinds}")
        if param.name == MEMORY_LIMIT:
            try:
                param = Parameter(param.name, value=parse_size(param.value))
            except ValueError as exc:
                raise LoadError(f"Extra component argument '{MEMORY_LIMIT}': {exc}") from None
        if param.name == CPU_QUOTA and not (
            math.isfinite(param.value) and CPU_QUOTA_RANGE[0] <= param.value <= CPU_QUOTA_RANGE[1]
        ):
            low, high = CPU_QUOTA_RANGE
            raise LoadError(
                f"Extra component argument '{CPU_QUOTA}' must be between {low:g} and "
                f"{high:g} (CPUs), got {param.value!r}"
            )
        if param.name == OOM_SCORE_ADJ and not OOM_SCORE_ADJ_RANGE[0] <= param.value <= OOM_SCORE_ADJ_RANGE[1]:
            raise LoadError(
                f"Extra component argument '{OOM_SCORE_ADJ}' must be from {OOM_SCORE_ADJ_RANGE[0]} "
                f"to {OOM_SCORE_ADJ_RANGE[1]}, got {param.value}"
            )
        if param.name == PROFILE and param.value not in PROFILES:
            raise LoadError(
                f"Extra component argument '{PROFILE}' must be one of {', '.join(PROFILES)}, got {param.value!r}"
            )
        extra[param.name] = param.value
    return extra


def _requested_name(namespace: str, name: str) -> str:
    """The full name a request gives its node (``/ns/name``), or "" if it
    leaves the name to the component."""
    if not name:
        return ""
    ns = namespace.strip("/")
    return f"/{ns}/{name}" if ns else f"/{name}"


def from_request(request: LoadNode.Request) -> NodeArguments:
    """Validate a ``LoadNode.Request`` and build the node's arguments."""
    rules = list(request.remap_rules)
    if request.node_name:
        rules.append(f"__node:={request.node_name}")
    if request.node_namespace:
        rules.append(f"__ns:={request.node_namespace}")
    cli_args = ["--ros-args"]
    for rule in rules:
        cli_args += ["-r", rule]
    extra = _extra_arguments(request.extra_arguments)
    return NodeArguments(
        cli_args=cli_args,
        parameter_overrides=_parameters(request.parameters),
        use_intra_process_comms=bool(extra.get("use_intra_process_comms", False)),
        forward_global_arguments=bool(extra.get("forward_global_arguments", False)),
        drop_loaded_event=seams.enabled() and bool(extra.get(seams.DROP_LOADED_EVENT, False)),
        cpu_quota=float(extra[CPU_QUOTA]) if CPU_QUOTA in extra else None,  # type: ignore[arg-type]
        memory_limit=int(extra[MEMORY_LIMIT]) if MEMORY_LIMIT in extra else None,  # type: ignore[call-overload]
        oom_score_adj=int(extra[OOM_SCORE_ADJ]) if OOM_SCORE_ADJ in extra else None,  # type: ignore[call-overload]
        profile=str(extra[PROFILE]) if PROFILE in extra else None,
        requested_name=_requested_name(request.node_namespace, request.node_name),
        plugin=request.plugin_name,
        log_level=request.log_level if request.log_level in LOG_LEVELS else 0,
        extra=extra,
    )
