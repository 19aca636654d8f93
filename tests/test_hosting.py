"""Thread mode's host (container/hosting.py) in this process: a node joins
the container's executor only when the manager lets it run, and never
after it was stopped (an UnloadNode sent on seeing LOADED can come first)."""

from composition_interfaces.srv import LoadNode
from ros_support import ros_nodes

from cloneguard.container import options, registry
from cloneguard.container.executors import NodesSingleThreadedExecutor
from cloneguard.container.hosting import ThreadHost


def _heartbeat():
    request = LoadNode.Request(package_name="cloneguard", plugin_name="cloneguard::Heartbeat")
    return registry.find(request.package_name, request.plugin_name).load_class(), options.from_request(request)


def test_a_node_runs_once_let_and_never_after_it_was_stopped():
    cls, args = _heartbeat()
    with ros_nodes("container", executor_class=NodesSingleThreadedExecutor) as ((container,), executor):
        host = ThreadHost(executor, container.context, container.get_logger())
        built = host.start(1, cls, args)
        assert built.node not in executor.get_nodes()  # built, not yet running
        host.run(built)
        assert built.node in executor.get_nodes()
        host.stop(built)
        assert built.node not in executor.get_nodes()

        early = host.start(2, cls, args)
        host.stop(early)  # the unload came first
        host.run(early)
        assert early.node not in executor.get_nodes()
