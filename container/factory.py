"""Build a component's node from its class and validated arguments."""
from __future__ import annotations

from rclpy.logging import LoggingSeverity
from rclpy.node import Node

from .options import LoadError, NodeArguments


def construct(cls: type[Node], args: NodeArguments, context) -> Node:
    """Instantiate ``cls``; any failure becomes a :class:`LoadError`."""
    try:
        node = cls(**args.node_kwargs(context))
    except Exception as exc:
        # Same wording as rclcpp_components for a throwing constructor.
        raise LoadError(
            f"Component constructor threw an exception: {type(exc).__name__}: {exc}"
        ) from None
    if not isinstance(node, Node):  # a class whose __new__ returns something else
        raise LoadError(f"Component {cls.__qualname__} did not produce an rclpy Node")
    if args.log_level:
        node.get_logger().set_level(LoggingSeverity(args.log_level))
    return node
