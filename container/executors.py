"""The executor thread mode's nodes spin on with
``--use_multi_threaded_executor``.

rclpy 7.1's ``MultiThreadedExecutor`` builds its wait set on one thread
while callbacks run on others. A callback that destroys a publisher or a
subscription (a lifecycle node's ``on_cleanup`` destroying its publisher,
the usual way) takes its event handlers off the node and then destroys
them; if the wait set being built had already taken a handler, adding it
raises ``InvalidHandle``, which escapes ``spin`` as if a callback had
raised, and that ends the container. The handler is off the node by then,
so the wait set is built again without it.

A waitable destroyed but left on its node would raise on every build: the
build is tried again only if the node's waitables changed since the one
that failed, else the error ends the container as before. No user callback
runs inside ``wait_for_ready_callbacks``: an ``InvalidHandle`` a callback
raises still ends the container, as with rclcpp.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rclpy.exceptions import InvalidHandle
from rclpy.executors import MultiThreadedExecutor

if TYPE_CHECKING:
    from typing import Any

    from rclpy.executors import WaitableEntityType
    from rclpy.node import Node
    from rclpy.task import Task


class NodesMultiThreadedExecutor(MultiThreadedExecutor):
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
