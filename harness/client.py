"""A typed client of a component container, over ROS 2 only.

It has its own rclpy Context on the container's domain and spins it on a
thread of its own, so tests call it like a plain object. Every call has a
timeout and raises :class:`HarnessTimeout` saying what did not happen.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import rclpy
from cloneguard_interfaces.msg import ComponentEvent
from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from rcl_interfaces.msg import Parameter as ParameterMsg
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from .errors import HarnessTimeout  # raised here; importable from here too

if TYPE_CHECKING:
    from typing import TypedDict, Unpack

    from rclpy.client import Client
    from rclpy.task import Task

    class LoadFields(TypedDict, total=False):
        """The keyword arguments of ContainerClient.load_request."""

        node_name: str
        node_namespace: str
        log_level: int
        remap_rules: Sequence[str]
        parameters: Mapping[str, object] | Sequence[ParameterMsg]
        extra_arguments: Mapping[str, object] | Sequence[ParameterMsg]


EVENT_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
# ROS's default service QoS keeps the last 10 responses a client has not
# taken yet: a burst of more concurrent calls from one client (the fuzzer's
# 16-load warm-up) lost the oldest answers while this client's spin thread
# waited for the GIL, and their callers timed out although the container had
# answered. The container keeps 1000 requests queued; keep as many answers.
SERVICE_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1000,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.VOLATILE,
)
EVENT_NAMES = {
    ComponentEvent.LOADED: "LOADED",
    ComponentEvent.UNLOADED: "UNLOADED",
    ComponentEvent.LOAD_FAILED: "LOAD_FAILED",
    ComponentEvent.CRASHED: "CRASHED",
    ComponentEvent.REPAIRED: "REPAIRED",
}


# ListNodes changes nothing: sent again after this long unanswered (call()).
LIST_RESEND_S = 2.0


@dataclass(frozen=True)
class Received:
    """A message and when (CLOCK_MONOTONIC ns) the harness got it."""

    msg: Any  # a message of the topic's type: any ROS message type
    at_ns: int


class Recorder:
    """Everything that arrives on one topic, with a way to wait for more."""

    def __init__(self, description: str):
        self.description = description
        self._cond = threading.Condition()
        self._items: list[Received] = []
        self._listeners: list = []

    def _add(self, msg: object) -> None:
        with self._cond:
            self._items.append(Received(msg, time.monotonic_ns()))
            self._cond.notify_all()
            listeners = list(self._listeners)
        for listener in listeners:  # outside our lock: they take their own
            listener(msg)

    def add_listener(self, fn: Callable[[Any], object]) -> None:
        """Call ``fn(msg)`` for every message from now on (on the spin thread)."""
        with self._cond:
            self._listeners.append(fn)

    def remove_listener(self, fn: Callable[[Any], object]) -> None:
        with self._cond:
            self._listeners.remove(fn)

    def items(self) -> list[Received]:
        with self._cond:
            return list(self._items)

    def messages(self) -> list:
        return [r.msg for r in self.items()]

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    def wait_for(self, predicate: Callable[[Any], object], timeout: float, what: str = "", since: int = 0) -> Any:
        """Wait until ``predicate(msg)`` holds for some message, from the
        ``since``-th on; return it."""
        scanned = since

        def first_match() -> Received | None:
            nonlocal scanned
            for item in self._items[scanned:]:
                if predicate(item.msg):
                    return item
            scanned = len(self._items)
            return None

        with self._cond:
            item = self._cond.wait_for(first_match, timeout)
            if item is None:
                raise HarnessTimeout(
                    f"no {what or 'matching message'} on {self.description} "
                    f"within {timeout:.1f} s ({len(self._items)} messages seen)"
                )
            return item.msg

    def wait_count(self, count: int, timeout: float) -> None:
        with self._cond:
            if not self._cond.wait_for(lambda: len(self._items) >= count, timeout):
                raise HarnessTimeout(
                    f"{self.description}: {len(self._items)} of {count} messages within {timeout:.1f} s"
                )


def to_parameter_msgs(values: Mapping[str, object]) -> list[ParameterMsg]:
    return [Parameter(name, value=value).to_parameter_msg() for name, value in values.items()]


class ContainerClient:
    def __init__(self, domain_id: int, container_fqn: str = "/ComponentManager", *, name: str = "harness"):
        self.container_fqn = container_fqn.rstrip("/") or "/ComponentManager"
        self._closed = False
        self._ctx = rclpy.Context()
        rclpy.init(context=self._ctx, domain_id=domain_id)
        self.node = Node(name, context=self._ctx)
        base = f"{self.container_fqn}/_container"
        self._load = self.node.create_client(LoadNode, f"{base}/load_node", qos_profile=SERVICE_QOS)
        self._unload = self.node.create_client(UnloadNode, f"{base}/unload_node", qos_profile=SERVICE_QOS)
        self._list = self.node.create_client(ListNodes, f"{base}/list_nodes", qos_profile=SERVICE_QOS)
        self.events = Recorder(f"{base}/component_events")
        self._event_sub = self.node.create_subscription(
            ComponentEvent, f"{base}/component_events", self.events._add, EVENT_QOS
        )
        self._subs: list = []
        self._executor = SingleThreadedExecutor(context=self._ctx)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name="harness-client", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            self._executor.spin()
        except Exception:  # closed under us (a spin close() did not see end in 5 s)
            if self._ctx.ok() and not self._closed:
                raise

    # -- generic --------------------------------------------------------------

    def call(self, client: Client, request: object, timeout: float = 10.0, *, resend_after: float | None = None) -> Any:
        """Call a service; wait for it to exist and answer within ``timeout``.

        ``resend_after`` (for requests that change nothing): send the request
        again each time that long passes unanswered. A server's response can
        be lost for good: rmw_fastrtps drops it ("client will not receive
        response") when the server has not yet matched the client's reply
        reader, which discovery under load can delay past its short wait."""
        deadline = time.monotonic() + timeout
        if not client.wait_for_service(timeout_sec=timeout):
            raise HarnessTimeout(f"service {client.srv_name} not available within {timeout:.1f} s")
        while True:
            done = threading.Event()
            future = client.call_async(request)
            future.add_done_callback(lambda _f, done=done: done.set())
            left = max(0.0, deadline - time.monotonic())
            if done.wait(min(left, resend_after) if resend_after else left):
                return future.result()
            client.remove_pending_request(future)
            if time.monotonic() >= deadline:
                raise HarnessTimeout(f"no answer from {client.srv_name} within {timeout:.1f} s")

    def run_on_spin_thread(self, fn: Callable[[], object]) -> Task:
        """A future of ``fn()``, called on the spin thread (between two of
        its callbacks, never during one)."""
        return self._executor.create_task(fn)

    def service_client(self, srv_type: type, name: str) -> Client:
        return self.node.create_client(srv_type, name, qos_profile=SERVICE_QOS)

    def subscribe(self, msg_type: type, topic: str, qos: QoSProfile | int = 10) -> Recorder:
        rec = Recorder(topic)
        self._subs.append(self.node.create_subscription(msg_type, topic, rec._add, qos))
        return rec

    # -- composition_interfaces -----------------------------------------------

    def load_request(
        self,
        package_name: str,
        plugin_name: str,
        *,
        node_name: str = "",
        node_namespace: str = "",
        log_level: int = 0,
        remap_rules: Sequence[str] = (),
        parameters: Mapping[str, object] | Sequence[ParameterMsg] = (),
        extra_arguments: Mapping[str, object] | Sequence[ParameterMsg] = (),
    ) -> LoadNode.Request:
        req = LoadNode.Request()
        req.package_name = package_name
        req.plugin_name = plugin_name
        req.node_name = node_name
        req.node_namespace = node_namespace
        req.log_level = log_level
        req.remap_rules = list(remap_rules)
        req.parameters = to_parameter_msgs(parameters) if isinstance(parameters, Mapping) else list(parameters)
        req.extra_arguments = (
            to_parameter_msgs(extra_arguments) if isinstance(extra_arguments, Mapping) else list(extra_arguments)
        )
        return req

    def load(
        self, package_name: str, plugin_name: str, *, timeout: float = 15.0, **fields: Unpack[LoadFields]
    ) -> LoadNode.Response:
        return self.send_load(self.load_request(package_name, plugin_name, **fields), timeout)

    def send_load(self, request: LoadNode.Request, timeout: float = 15.0) -> LoadNode.Response:
        """A LoadNode request as it is, however odd its fields."""
        return self.call(self._load, request, timeout)

    def load_ok(self, package_name: str, plugin_name: str, **fields: Unpack[LoadFields]) -> LoadNode.Response:
        """Load and insist that it worked."""
        resp = self.load(package_name, plugin_name, **fields)
        if not resp.success:
            raise AssertionError(f"LoadNode {package_name}/{plugin_name} failed: {resp.error_message}")
        return resp

    def unload(self, unique_id: int, *, timeout: float = 10.0) -> UnloadNode.Response:
        req = UnloadNode.Request()
        req.unique_id = unique_id
        return self.call(self._unload, req, timeout)

    def list(self, *, timeout: float = 10.0) -> list[tuple[int, str]]:
        resp = self.call(self._list, ListNodes.Request(), timeout, resend_after=LIST_RESEND_S)
        return list(zip(resp.unique_ids, resp.full_node_names, strict=True))

    def wait_for_event(self, event_type: int, *, unique_id: int | None = None, timeout: float = 10.0) -> ComponentEvent:
        def match(ev: ComponentEvent) -> bool:
            return ev.event_type == event_type and (unique_id is None or ev.unique_id == unique_id)

        what = EVENT_NAMES.get(event_type, str(event_type)) + (f" for unique_id {unique_id}" if unique_id else "")
        return self.events.wait_for(match, timeout, what)

    def nodes_by_pid(self) -> dict[int, str]:
        """Every node process the events named (LOADED, CRASHED): pid -> full name."""
        return {
            e.pid: e.full_node_name
            for e in self.events.messages()
            if e.event_type in (ComponentEvent.LOADED, ComponentEvent.CRASHED) and e.pid
        }

    def dead_pids(self) -> set[int]:
        """The node processes a CRASHED event said died."""
        return {e.pid for e in self.events.messages() if e.event_type == ComponentEvent.CRASHED}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        # The spin thread ends before the node goes: rclpy 7.1's shutdown()
        # does not wait for a spin in progress, and destroying the node under
        # one (its guard conditions) raised in it (AttributeError: 'NoneType'
        # object has no attribute 'handle', seen in slow runs).
        self._executor.shutdown(timeout_sec=1.0)
        self._thread.join(timeout=5.0)
        self.node.destroy_node()
        self._ctx.try_shutdown()

    def __enter__(self) -> ContainerClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
