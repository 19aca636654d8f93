"""``component_container``: the one executable, in every mode.

    component_container                                # single-threaded executor
    component_container --use_multi_threaded_executor  # multi-threaded executor
    component_container --isolated                     # a clone(CLONE_VM) child per node

ROS arguments (``--ros-args -r __node:=name -r __ns:=/ns ...``) apply to the
container's own node, named ``ComponentManager`` by default.
"""
from __future__ import annotations

import argparse
import sys

import rclpy
from rclpy.executors import (
    ExternalShutdownException,
    MultiThreadedExecutor,
    SingleThreadedExecutor,
)
from rclpy.node import Node
from rclpy.utilities import remove_ros_args

from .hosting import ThreadHost
from .manager import ComponentManager

DEFAULT_NODE_NAME = "ComponentManager"


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="component_container",
        description="ROS 2 component container (rclpy) with optional per-node "
        "clone(CLONE_VM) process isolation.",
    )
    parser.add_argument(
        "--use_multi_threaded_executor", "--use-multi-threaded-executor",
        action="store_true",
        help="spin the container's nodes on a multi-threaded executor",
    )
    parser.add_argument(
        "--isolated", action="store_true",
        help="run each loaded node's executor in its own clone(CLONE_VM) process",
    )
    return parser.parse_args(argv)


def _make_host(opts, executor, context):
    if opts.isolated:
        raise SystemExit(
            "component_container: --isolated is not available yet: per-node "
            "clone(CLONE_VM) isolation is not implemented in this version"
        )
    return ThreadHost(executor, context)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv if argv is None else argv)
    opts = parse_args(remove_ros_args(argv)[1:])
    rclpy.init(args=argv)
    context = rclpy.get_default_context()
    node = Node(DEFAULT_NODE_NAME, context=context)
    executor = (
        MultiThreadedExecutor(context=context)
        if opts.use_multi_threaded_executor
        else SingleThreadedExecutor(context=context)
    )
    try:
        host = _make_host(opts, executor, context)
    except SystemExit:
        node.destroy_node()
        rclpy.try_shutdown()
        raise
    manager = ComponentManager(node, host)
    executor.add_node(node)
    node.get_logger().info(
        f"{node.get_fully_qualified_name()} ready "
        f"({'multi' if opts.use_multi_threaded_executor else 'single'}-threaded executor)"
    )
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        manager.close()
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
