"""Turn a LoadNode request into the arguments a component's Node is built with.

Everything here is validation and translation; nothing is constructed. A bad
request raises :class:`LoadError` with a message that says what is wrong, and
the manager answers ``success=false`` with it before it touches any state.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from rclpy.exceptions import InvalidNamespaceException, InvalidNodeNameException
from rclpy.parameter import Parameter
from rclpy.validate_namespace import validate_namespace
from rclpy.validate_node_name import validate_node_name

# rcutils log severities a LoadNode.log_level may carry (0 means "unset").
LOG_LEVELS = {10: "debug", 20: "info", 30: "warn", 40: "error", 50: "fatal"}

# extra_arguments this container understands, and the type each must have.
# DROP_LOADED_EVENT is a fault-injection hook for the harness: the node loads
# normally but its LOADED event is not published (a lost event).
# CPU_QUOTA (CPUs, e.g. 0.5) puts an isolated node in a cgroup with that quota.
DROP_LOADED_EVENT = "cloneguard.fault.drop_loaded_event"
CPU_QUOTA = "cloneguard.cpu_quota"
KNOWN_EXTRA_ARGUMENTS = {
    "use_intra_process_comms": Parameter.Type.BOOL,
    DROP_LOADED_EVENT: Parameter.Type.BOOL,
    CPU_QUOTA: Parameter.Type.DOUBLE,
}
_TYPE_NAMES = {Parameter.Type.BOOL: "a boolean", Parameter.Type.DOUBLE: "a double"}


class LoadError(Exception):
    """A LoadNode request that cannot be honoured; str() is the answer's text."""


@dataclass(frozen=True)
class NodeArguments:
    """What a component's constructor receives, already validated."""

    cli_args: list[str]
    parameter_overrides: list[Parameter]
    use_intra_process_comms: bool = False
    drop_loaded_event: bool = False
    cpu_quota: float | None = None
    log_level: int = 0
    extra: dict[str, object] = field(default_factory=dict)

    def node_kwargs(self, context) -> dict:
        """Keyword arguments for ``rclpy.node.Node.__init__``."""
        return {
            "context": context,
            "cli_args": list(self.cli_args),
            "use_global_arguments": False,
            "parameter_overrides": list(self.parameter_overrides),
        }


def _node_name_rule(name: str) -> str:
    try:
        validate_node_name(name)
    except InvalidNodeNameException as exc:
        raise LoadError(str(exc)) from None
    return f"__node:={name}"


def _namespace_rule(namespace: str) -> str:
    # launch_ros sends relative namespaces as written by users; rcl needs them
    # fully qualified, so a relative one is taken as relative to the root.
    if not namespace.startswith("/"):
        namespace = "/" + namespace
    try:
        validate_namespace(namespace)
    except InvalidNamespaceException as exc:
        raise LoadError(str(exc)) from None
    return f"__ns:={namespace}"


def _checked_remap_rule(rule: str) -> str:
    lhs, sep, rhs = rule.partition(":=")
    if not sep or not lhs or not rhs or any(c.isspace() for c in rule):
        raise LoadError(
            f"Invalid remap rule {rule!r}: expected 'from:=to' with no spaces"
        )
    return rule


def _parameters(messages) -> list[Parameter]:
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


def _extra_arguments(messages) -> dict[str, object]:
    extra = {}
    for param in _parameters(messages):
        wanted = KNOWN_EXTRA_ARGUMENTS.get(param.name)
        if wanted is not None and param.type_ != wanted:
            raise LoadError(
                f"Extra component argument '{param.name}' must be {_TYPE_NAMES[wanted]}"
            )
        if param.name == CPU_QUOTA and not param.value > 0:
            raise LoadError(f"Extra component argument '{CPU_QUOTA}' must be positive, got {param.value}")
        extra[param.name] = param.value
    return extra


def from_request(request) -> NodeArguments:
    """Validate a ``LoadNode.Request`` and build the node's arguments."""
    rules = []
    if request.node_name:
        rules.append(_node_name_rule(request.node_name))
    if request.node_namespace:
        rules.append(_namespace_rule(request.node_namespace))
    rules.extend(_checked_remap_rule(r) for r in request.remap_rules)
    if request.log_level and request.log_level not in LOG_LEVELS:
        raise LoadError(
            f"Invalid log_level {request.log_level}: expected 0 (unset) or one of "
            + ", ".join(f"{k} ({v})" for k, v in LOG_LEVELS.items())
        )
    cli_args = ["--ros-args"]
    for rule in rules:
        cli_args += ["-r", rule]
    extra = _extra_arguments(request.extra_arguments)
    return NodeArguments(
        cli_args=cli_args,
        parameter_overrides=_parameters(request.parameters),
        use_intra_process_comms=bool(extra.get("use_intra_process_comms", False)),
        drop_loaded_event=bool(extra.get(DROP_LOADED_EVENT, False)),
        cpu_quota=extra.get(CPU_QUOTA),
        log_level=request.log_level,
        extra=extra,
    )
