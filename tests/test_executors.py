"""The executor thread mode's nodes spin on with a multi-threaded executor
(container/executors.py): a publisher destroyed by a callback while the
wait set is being built does not end the spin.

The interleaving is made exactly, with real rclpy entities: a waitable
added after the publisher's event handlers destroys the publisher when the
build takes it, after the build took the handlers and before it adds them
(rclpy takes every waitable, then adds every one).
"""

import threading
import time

import pytest
from rclpy.exceptions import InvalidHandle
from rclpy.executors import MultiThreadedExecutor
from rclpy.task import Future
from rclpy.waitable import NumberOfEntities, Waitable
from ros_support import ros_nodes
from std_msgs.msg import String

from cloneguard.container.executors import NodesMultiThreadedExecutor, NodesSingleThreadedExecutor


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


# A node's work after its unload (NodeWork). The interleaving of the CI
# failure, made exactly: a node's callback completes a future whose done
# callback publishes on the node's publisher (fixtures/node_kinds.py's
# Clients node does this with each response); the node is removed and
# destroyed while that callback is still running, before the done callback
# (a task of its own) has run.

EXECUTORS = {"single": NodesSingleThreadedExecutor, "multi": NodesMultiThreadedExecutor}


class _CompletesAFuture:
    """On ``node``'s first timer tick: complete a future whose done callback
    publishes on ``node`` (once ``complete`` is set, if given), then wait
    for ``go_on`` before returning."""

    def __init__(self, node, executor, complete: threading.Event | None = None):
        self.publisher = node.create_publisher(String, "done", 10)
        self.in_callback, self.go_on = threading.Event(), threading.Event()
        self.completed, self.done_callback_ran = threading.Event(), threading.Event()
        self._executor = executor
        self._complete = complete
        self._timer = node.create_timer(0.01, self._tick)

    def _tick(self):
        self._timer.cancel()
        self.in_callback.set()
        assert self._complete is None or self._complete.wait(10)
        future = Future(executor=self._executor)
        future.add_done_callback(self._publish)
        future.set_result(None)  # its done callback is now a task of the executor
        self.completed.set()
        assert self.go_on.wait(10)

    def _publish(self, _future):
        self.done_callback_ran.set()
        self.publisher.publish(String(data="done"))


def _turns(executor, times):
    """Let the executor go round its loop ``times`` times (a task of no node,
    created after the last turn, has run each time)."""
    for _ in range(times):
        turned = threading.Event()
        executor.create_task(turned.set)
        assert turned.wait(10), "the executor stopped going round"


@pytest.mark.parametrize("kind", list(EXECUTORS))
def test_a_nodes_pending_done_callback_never_runs_once_it_is_retired(kind):
    """A response handled as the node's unload begins: its done callback,
    a task of the node made once retire() began, never runs. (Made before,
    a multi-threaded executor may run it at once on another thread, the
    node still on it, as rclpy's own does: the CI failure was one that ran
    after the node was destroyed.)"""
    with ros_nodes("owner", executor_class=EXECUTORS[kind]) as ((node,), executor):
        retiring_began = threading.Event()
        owner = _CompletesAFuture(node, executor, complete=retiring_began)
        failure: list[Exception] = []
        spinner = threading.Thread(target=lambda: _spin_catching(executor, failure))
        spinner.start()
        try:
            assert owner.in_callback.wait(10)
            executor.remove_node(node)
            retired = []
            retiring = threading.Thread(target=lambda: retired.append(executor.retire(node, 10.0)))
            retiring.start()
            deadline = time.monotonic() + 10
            while node not in executor._retired:  # retire() has begun: none of the node's work starts
                assert time.monotonic() < deadline, "retire() did not begin"
                time.sleep(0.001)
            retiring_began.set()
            assert owner.completed.wait(10)  # its done callback is a pending task of the node now
            retiring.join(0.3)
            assert retiring.is_alive(), "retire returned while a callback of the node was running"
            owner.go_on.set()
            retiring.join(10)
            assert retired == [True]
            node.destroy_publisher(owner.publisher)  # as destroying the node does
            _turns(executor, 3)
            assert not owner.done_callback_ran.is_set()
        finally:
            owner.go_on.set()
            executor.shutdown()
            spinner.join(10)
        assert failure == []


def test_rclpys_executor_runs_that_done_callback_after_the_node_is_gone():
    """The same with rclpy's executor: the done callback belongs to no node
    and runs after it, on the destroyed publisher."""
    with ros_nodes("owner") as ((node,), executor):
        owner = _CompletesAFuture(node, executor)
        failure: list[Exception] = []
        spinner = threading.Thread(target=lambda: _spin_catching(executor, failure))
        spinner.start()
        assert owner.in_callback.wait(10)
        executor.remove_node(node)
        node.destroy_publisher(owner.publisher)
        owner.go_on.set()
        spinner.join(10)
        assert owner.done_callback_ran.is_set()
        assert [type(exc) for exc in failure] == [InvalidHandle]


def test_retire_says_when_a_callback_of_the_node_still_runs():
    with ros_nodes("owner", executor_class=NodesSingleThreadedExecutor) as ((node,), executor):
        owner = _CompletesAFuture(node, executor)
        spinner = threading.Thread(target=lambda: _spin_catching(executor, []))
        spinner.start()
        try:
            assert owner.in_callback.wait(10)
            executor.remove_node(node)
            assert executor.retire(node, 0.05) is False
            # Its pending done callback is cancelled all the same: left, it
            # would stay in the executor's task list for good.
            assert [t for t, _, n in executor._tasks if n is node and not t.executing() and not t.cancelled()] == []
            owner.go_on.set()
            assert executor.retire(node, 10.0) is True
        finally:
            owner.go_on.set()
            executor.shutdown()
            spinner.join(10)


def _spin_catching(executor, failure):
    try:
        executor.spin()
    except Exception as exc:
        failure.append(exc)
