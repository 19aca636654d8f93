"""The harness client sends a ListNodes again when it goes unanswered: a
response can be lost for good (harness/client.py: call)."""

from __future__ import annotations

import threading
import time

import rclpy
from composition_interfaces.srv import ListNodes
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor

from cloneguard.harness.client import ContainerClient
from cloneguard.harness.domains import lease


def test_an_unanswered_list_nodes_is_sent_again_and_the_answer_taken():
    held = lease()
    context = Context()
    rclpy.init(context=context, domain_id=held.domain_id)
    server = rclpy.create_node("fake_manager", context=context)
    seen: list[float] = []
    release = threading.Event()

    def answer(request, response):
        seen.append(time.monotonic())
        if len(seen) == 1:
            release.wait(10)  # the first request is answered only at the end (as if lost)
        response.unique_ids = [7]
        response.full_node_names = ["/n"]
        return response

    server.create_service(
        ListNodes, "/fake_manager/_container/list_nodes", answer, callback_group=ReentrantCallbackGroup()
    )
    executor = MultiThreadedExecutor(num_threads=2, context=context)
    executor.add_node(server)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    client = ContainerClient(held.domain_id, "/fake_manager")
    try:
        resp = client.call(client._list, ListNodes.Request(), timeout=10.0, resend_after=0.5)
        assert list(resp.unique_ids) == [7]
        assert len(seen) >= 2, "the request was not sent again"
        assert not release.is_set()
    finally:
        release.set()
        client.close()
        executor.shutdown()
        server.destroy_node()
        rclpy.shutdown(context=context)
        spinner.join(5)
        held.release()
