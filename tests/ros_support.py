"""ROS nodes inside the test process, for tests of code that runs in one."""

from contextlib import contextmanager

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from cloneguard.container import intra
from cloneguard.harness.domains import lease


@contextmanager
def ros_nodes(*names: str, executor_class=SingleThreadedExecutor):
    """Nodes in this process on a leased ROS domain (the harness plugin has
    already pointed Fast DDS at the loopback-only profile), all on one
    executor (of ``executor_class``) that the caller spins: yields (nodes,
    executor)."""
    held = lease()
    context = Context()
    rclpy.init(context=context, domain_id=held.domain_id)
    nodes = [rclpy.create_node(name, context=context) for name in names]
    executor = executor_class(context=context)
    for node in nodes:
        executor.add_node(node)
    try:
        yield nodes, executor
    finally:
        executor.shutdown()
        for node in nodes:
            intra.api.destroy_endpoints(node)
            node.destroy_node()
        rclpy.shutdown(context=context)
        held.release()
