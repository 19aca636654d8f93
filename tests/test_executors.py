"""The executor thread mode's nodes spin on with a multi-threaded executor
(container/executors.py): a publisher destroyed by a callback while the
wait set is being built does not end the spin.

The interleaving is made exactly, with real rclpy entities: a waitable
added after the publisher's event handlers destroys the publisher when the
build takes it, after the build took the handlers and before it adds them
(rclpy takes every waitable, then adds every one).
"""

import pytest
from rclpy.exceptions import InvalidHandle
from rclpy.executors import MultiThreadedExecutor
from rclpy.waitable import NumberOfEntities, Waitable
from ros_support import ros_nodes
from std_msgs.msg import String

from cloneguard.container.executors import NodesMultiThreadedExecutor


class _DestroysWhenTaken(Waitable):
    """Destroys ``publisher`` the first time a wait set takes this."""

    def __init__(self, node, publisher):
        super().__init__(node.default_callback_group)
        self._node, self._publisher = node, publisher
        self.destroyed = False

    def __enter__(self):
        if not self.destroyed:
            self.destroyed = self._node.destroy_publisher(self._publisher)

    def __exit__(self, *exc):
        pass

    def get_num_entities(self):
        return NumberOfEntities()

    def add_to_wait_set(self, wait_set):
        pass

    def is_ready(self, wait_set):
        return False


class _Stale(_DestroysWhenTaken):
    """Destroys only the publisher's event handlers, leaving them on the
    node: every wait set build raises."""

    def __enter__(self):
        for handler in self._publisher.event_handlers:
            handler.destroy()
        self.destroyed = True


def _spin_with(executor_class, waitable_class):
    with ros_nodes("churn") as ((node,), _):
        publisher = node.create_publisher(String, "churned", 10)
        assert publisher.event_handlers, "rclpy 7.1 gives a publisher its default event handlers"
        waitable = waitable_class(node, publisher)
        node.add_waitable(waitable)
        executor = executor_class(context=node.context)
        executor.add_node(node)
        try:
            executor.spin_once(timeout_sec=0.05)
        finally:
            executor.shutdown()
            node.remove_waitable(waitable)
        return waitable


def test_rclpys_executor_ends_its_spin_on_that_interleaving():
    with pytest.raises(InvalidHandle):
        _spin_with(MultiThreadedExecutor, _DestroysWhenTaken)


def test_the_containers_builds_the_wait_set_again_without_the_destroyed_publisher():
    assert _spin_with(NodesMultiThreadedExecutor, _DestroysWhenTaken).destroyed


def test_a_waitable_destroyed_but_left_on_its_node_still_ends_the_spin():
    with pytest.raises(InvalidHandle):
        _spin_with(NodesMultiThreadedExecutor, _Stale)
