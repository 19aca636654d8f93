"""The executors thread mode's nodes spin on, and what they add to rclpy's.

**Work on behalf of a node.** rclpy 7.1 runs a future's done callback as a
task of no node: a client's response handled by node N's executor turns N's
``add_done_callback`` callback into a task that still runs after N was
removed and destroyed, and raises ``InvalidHandle`` when it touches N's
publisher; that ended the container at an unload (seen in CI: a client's
done callback publishing just after its node's unload). Here a task created
while one of a node's callbacks runs belongs to that node, as rclpy's own
entity tasks do: the executor runs it only while the node is on it.
:meth:`NodeWork.retire` (at an unload, after ``remove_node``) waits until
none of the node's work is running, then cancels what is left of it, so the
node is destroyed under nothing of its own, as rclcpp's containers, whose
callbacks hold their entities alive.

**A wait set built while a callback destroys a publisher.** rclpy 7.1's
``MultiThreadedExecutor`` builds its wait set on one thread while callbacks
run on others. A callback that destroys a publisher or a subscription (a
lifecycle node's ``on_cleanup`` destroying its publisher, the usual way)
takes its event handlers off the node and then destroys them; if the wait
set being built had already taken a handler, adding it raises
``InvalidHandle``, which escapes ``spin`` as if a callback had raised, and
that ends the container. The handler is off the node by then, so the wait
set is built again without it. A waitable destroyed but left on its node
would raise on every build: the build is tried again only if the node's
waitables changed since the one that failed, else the error ends the
container as before. No user callback runs inside
``wait_for_ready_callbacks``: an ``InvalidHandle`` a callback raises still
ends the container, as with rclcpp.

**What of rclpy's executor this relies on** (checked when one is made,
:data:`RCLPY_EXECUTOR_PARTS`): its task list ``_tasks`` of ``(task, entity,
node)``, where a task with a node runs only while that node is on the
executor, guarded by ``_tasks_lock``; ``_guard``, the guard condition that
wakes its wait; and ``_cb_iter``, the generator of ready callbacks that
``wait_for_ready_callbacks`` resumes.
"""

from __future__ import annotations

import threading
import weakref
from collections import Counter
from typing import TYPE_CHECKING

from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.task import Task

if TYPE_CHECKING:
    from typing import Any

    from rclpy.executors import WaitableEntityType
    from rclpy.node import Node

RCLPY_EXECUTOR_PARTS = ("_tasks", "_tasks_lock", "_guard", "_cb_iter")

_running_for = threading.local()  # .node: the node whose work this thread is running, if any


class _NodesTask:
    """A task the executor hands out to run on behalf of ``node``: while it
    runs, the tasks it creates are the node's too. Everything else is the
    task's own (the executors ask it ``done()``, ``result()``, ...)."""

    def __init__(self, task: Task, node: Node, work: NodeWork) -> None:
        self._task, self._node, self._work = task, node, work

    def __call__(self) -> None:
        if not self._work._begin(self._node):
            # The node was retired after its wait set was built: a handler
            # that wait made for it never runs.
            self._task.cancel()
            return
        outer = getattr(_running_for, "node", None)
        _running_for.node = self._node
        try:
            self._task()
        finally:
            _running_for.node = outer
            self._work._end(self._node)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._task, name)


class NodeWork(Executor):
    """An rclpy executor whose tasks belong to the node they were created
    for (see the module's docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        missing = [part for part in RCLPY_EXECUTOR_PARTS if not hasattr(self, part)]
        if missing:
            raise RuntimeError(
                f"this rclpy's executor has no {', '.join(missing)}: cloneguard's thread mode was written "
                "against rclpy 7.1 (ROS 2 Jazzy), whose executor keeps its tasks there"
            )
        self._work_changed = threading.Condition()
        self._running: Counter[int] = Counter()  # id(node) -> callbacks of it running now
        self._retired: weakref.WeakSet[Node] = weakref.WeakSet()

    def create_task(self, callback: Any, *args: Any, **kwargs: Any) -> Task:
        node = getattr(_running_for, "node", None)
        if node is None:
            return super().create_task(callback, *args, **kwargs)
        task = Task(callback, args, kwargs, executor=self)
        with self._tasks_lock:
            self._tasks.append((task, None, node))
            self._guard.trigger()
        return task

    def wait_for_ready_callbacks(self, *args: Any, **kwargs: Any) -> tuple[Task, WaitableEntityType, Node]:
        ready: tuple[Task, WaitableEntityType, Node] = super().wait_for_ready_callbacks(*args, **kwargs)
        handler, entity, node = ready
        if node is None:
            return ready
        return _NodesTask(handler, node, self), entity, node  # type: ignore[return-value]  # a Task to its callers

    def retire(self, node: Node, timeout: float) -> bool:
        """After ``remove_node(node)``: none of the node's work starts any
        more; wait until none of it is running, then cancel what is left (it
        would never run, and would stay in the task list for good). False if
        some still ran after ``timeout`` seconds (that is left to end)."""
        with self._work_changed:
            self._retired.add(node)
            ended = self._work_changed.wait_for(lambda: not self._running[id(node)], timeout)
            with self._tasks_lock:
                left = [task for task, _entity, owner in self._tasks if owner is node and not task.executing()]
            for task in left:
                task.cancel()
        return ended

    def _begin(self, node: Node) -> bool:
        with self._work_changed:
            if node in self._retired:
                return False
            self._running[id(node)] += 1
            return True

    def _end(self, node: Node) -> None:
        with self._work_changed:
            self._running[id(node)] -= 1
            if not self._running[id(node)]:
                del self._running[id(node)]
                self._work_changed.notify_all()


class NodesSingleThreadedExecutor(NodeWork, SingleThreadedExecutor):
    """Thread mode's executor (rclpy's, with :class:`NodeWork`)."""


class NodesMultiThreadedExecutor(NodeWork, MultiThreadedExecutor):
    """Thread mode's executor with ``--use_multi_threaded_executor``."""

    def wait_for_ready_callbacks(self, *args: Any, **kwargs: Any) -> tuple[Task, WaitableEntityType, Node]:
        failed_with = None
        while True:
            try:
                return super().wait_for_ready_callbacks(*args, **kwargs)
            except InvalidHandle:
                waitables = [id(w) for node in self.get_nodes() for w in node.waitables]
                if waitables == failed_with:
                    raise
                failed_with = waitables
                self._cb_iter = None  # that generator ended with the raise; build anew
