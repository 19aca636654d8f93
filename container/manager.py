"""The component manager: LoadNode / UnloadNode / ListNodes and their events.

It owns the table of loaded nodes and the unique-id counter; it validates a
request, asks the host to start or stop a node, and publishes what happened.
Its behaviour follows rclcpp_components' ComponentManager: ids start at 1 and
are never reused (a load that fails after an id was taken still uses it up),
a failed load answers unique_id 0 and an empty full_node_name.

Deaths come from the host (isolated mode), on the core's listener thread: the node
leaves the table, a CRASHED event goes out, and with a restart policy the
same request is loaded again after a backoff, up to a limit of restarts in
a row (restart.py); the CRASHED event says which.

No request can stop the container serving others. The services share a
reentrant callback group (the command line spins this node on an executor
of its own, with several threads); a node is built on a thread of its own,
which a LoadNode waits for at most CONSTRUCT_WAIT_S (a constructor that
never returns is answered as a failure, and its node is stopped if it ever
appears); and an unexpected exception anywhere in a request is that
request's failure (``success=false``, the cause named, the traceback logged
once), never the container's end. What a request echoes back is bounded and
escaped (``shown``).
"""

from __future__ import annotations

import threading
import traceback
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.qos import QoSProfile, qos_profile_services_default

from . import diagnostics, events, intra, memory_budget, options, registry, repairs, seams
from .events import EventPublisher
from .hosting import Host, Hosted, NodeDeath
from .options import LoadError
from .restart import Lineage, RestartPolicy, uptime

if TYPE_CHECKING:
    from collections.abc import Callable
    from typing import TypeAlias, TypedDict, Unpack

    from rclpy.impl.rcutils_logger import RcutilsLogger
    from rclpy.node import Node

    from .options import NodeArguments

    # A service's request and response (LoadNode, UnloadNode or ListNodes).
    _Request: TypeAlias = LoadNode.Request | UnloadNode.Request | ListNodes.Request
    _Response: TypeAlias = LoadNode.Response | UnloadNode.Response | ListNodes.Response

    class _CrashFields(TypedDict, total=False):
        """What a CRASHED event says beyond the node (``_publish``'s extra fields)."""

        error_message: str
        exit_signal: int
        exit_code: int
        allocator_quarantined: bool


#: How many dead nodes the manager remembers, for the REPAIRED events that
#: name them (a repair comes within seconds of its death).
DIED_KEPT = 256


class _Unanswered:
    """Requests taken and not yet answered. rclpy sends what a handler
    returns once the handler has returned, and rclpy 7.1's
    ``Executor.shutdown`` does not wait for callbacks in flight: stopping
    waits here, so that a request answered while the container stops (a
    load still waiting for its node) reaches its caller."""

    def __init__(self) -> None:
        self._count = 0
        self._changed = threading.Condition()

    def counted(
        self, handler: Callable[[_Request, _Response], _Response]
    ) -> Callable[[_Request, _Response], _Response]:
        def taken(request: _Request, response: _Response) -> _Response:
            with self._changed:
                self._count += 1
            return handler(request, response)

        return taken

    def answering(self, send: Callable[[_Response, Any], None]) -> Callable[[_Response, Any], None]:
        # header: rclpy's rmw_request_id_t or rmw_service_info_t (pybind11, untyped)
        def send_response(response: _Response, header: Any) -> None:
            try:
                send(response, header)
            finally:
                with self._changed:
                    self._count -= 1
                    self._changed.notify_all()

        return send_response

    def wait(self, timeout: float) -> int:
        """Wait until every request taken is answered; how many are not."""
        with self._changed:
            self._changed.wait_for(lambda: self._count == 0, timeout)
            return self._count


@dataclass
class _Entry:
    hosted: Hosted
    spec: registry.ComponentSpec
    request: LoadNode.Request
    lineage: Lineage


def _qos_fields(profile: QoSProfile) -> dict:
    return {"history": profile.history, "reliability": profile.reliability, "durability": profile.durability}


def shown(text: str, limit: int = 500) -> str:
    """``text`` as an answer or a log line may carry it: control characters
    escaped, at most ``limit`` characters (plus how many were cut)."""
    out = "".join(c if c.isprintable() or c == " " else repr(c)[1:-1] for c in text[:limit])
    return out + (f"... ({len(text) - limit} more characters)" if len(text) > limit else "")


class ComponentManager:
    # How long a LoadNode waits for its node to be built (the isolated host
    # gives up on a child after 60 s of its own).
    CONSTRUCT_WAIT_S = 65.0
    # How often repairs recorded by any task are published as REPAIRED events.
    REPAIR_POLL_S = 0.05
    # Threads that build nodes: reused (a thread per load would churn
    # stacks and arenas); more than one, so that constructors that never
    # return do not hold up the rest.
    BUILDERS = 8
    # Requests a service keeps queued while its threads are busy.
    REQUEST_QUEUE = 1000

    def __init__(
        self,
        node: Node,
        host: Host,
        *,
        logger: RcutilsLogger | None = None,
        restart_limit: int | None = None,
        diagnostics_period_s: float = diagnostics.PERIOD_S,
    ) -> None:
        """``restart_limit``: reload a node whose process died (restart.py),
        at most that many times in a row; None: never. ``diagnostics_period_s``:
        between two publications of the nodes' statuses (diagnostics.py)."""
        self._node = node
        self._host = host
        self._log = logger or node.get_logger()
        self._events = EventPublisher(node)
        self._lock = threading.Lock()  # guards the fields below
        self._built = threading.Condition(self._lock)  # a start ended, or stopping began
        self._stopping = False
        self._next_id = 1
        self._loaded: dict[int, _Entry] = {}
        # The last DIED_KEPT nodes whose process died, for the REPAIRED
        # events that name them after their death.
        self._died: OrderedDict[int, _Entry] = OrderedDict()
        self._starting: set[int] = set()  # ids whose host.start() is running
        self._early_deaths: dict[int, NodeDeath] = {}  # deaths seen while starting
        self._unanswered = _Unanswered()
        self._builders = ThreadPoolExecutor(self.BUILDERS, thread_name_prefix="cloneguard-build")
        self._restarts = None if restart_limit is None else RestartPolicy(node, self.reload, limit=restart_limit)
        host.report_deaths_to(self.on_death)
        # A node's CRASHED then goes out from the host's core where it can
        # (isolated mode, no restart policy: arm_crashed below).
        host.publish_crashed_with(self._events)
        # The intra-process bus is container-owned: made here, before any child.
        intra.get_bus()
        group = ReentrantCallbackGroup()
        # ROS's default service queue keeps 10 requests: an eleventh that
        # arrives while they wait is dropped, never answered. Keep more.
        qos = QoSProfile(**{**_qos_fields(qos_profile_services_default), "depth": self.REQUEST_QUEUE})
        for srv_type, name, handler in (
            (LoadNode, "load_node", self._on_load_node),
            (UnloadNode, "unload_node", self._on_unload_node),
            (ListNodes, "list_nodes", self._on_list_nodes),
        ):
            counted = self._unanswered.counted(handler)
            srv = node.create_service(srv_type, f"~/_container/{name}", counted, qos_profile=qos, callback_group=group)
            # The service's own send_response, wrapped (mypy: no assigning to a method).
            srv.send_response = self._unanswered.answering(srv.send_response)  # type: ignore[method-assign,assignment]
        # Repairs recorded by whichever task did them (repairs.py), published here.
        self._repair_timer = node.create_timer(self.REPAIR_POLL_S, self.publish_repairs)
        self._diagnostics_timer = diagnostics.publish_every(node, diagnostics_period_s, self._figures)

    # -- services -------------------------------------------------------------

    def _on_load_node(self, request: LoadNode.Request, response: LoadNode.Response) -> LoadNode.Response:
        return self._contained("LoadNode", self._load, request, response, None)

    def _contained(
        self,
        what: str,
        handler: Callable[..., _Response],
        request: _Request,
        response: _Response,
        *args: Lineage | None,
    ) -> _Response:
        """Run a request; an exception nobody expected fails that request only."""
        try:
            return handler(request, response, *args)
        except Exception as exc:
            self._log.error(f"{what} failed unexpectedly:\n" + "".join(traceback.format_exception(exc)))
            message = shown(f"internal error: {type(exc).__name__}: {exc}")
            if isinstance(response, LoadNode.Response):
                return self._load_failed(request, response, message)
            response.success = False
            if hasattr(response, "error_message"):
                response.error_message = message
            return response

    def _load(
        self, request: LoadNode.Request, response: LoadNode.Response, lineage: Lineage | None
    ) -> LoadNode.Response:
        try:
            spec = registry.find(request.package_name, request.plugin_name)
            args = options.from_request(request)
            cls = spec.load_class()
        except LoadError as exc:
            return self._load_failed(request, response, str(exc), exc.log_detail)
        if args.forward_global_arguments:
            self._log.warning(options.FORWARD_GLOBAL_WARNING)
        unique_id = self._take_id()
        try:
            hosted = self._start(unique_id, cls, args)
        except BaseException as exc:  # whatever the start raised fails this load only
            intra.get_bus().forget(unique_id)  # what a failed constructor registered
            with self._lock:
                self._starting.discard(unique_id)
            if not isinstance(exc, LoadError):
                self._log.error(
                    f"unique_id {unique_id}: starting the node failed unexpectedly:\n"
                    + "".join(traceback.format_exception(exc))
                )
                exc = LoadError(f"internal error: {type(exc).__name__}: {exc}")
            return self._load_failed(request, response, str(exc))
        entry = _Entry(hosted, spec, request, lineage or Lineage(hosted.full_node_name))
        with self._lock:
            self._starting.discard(unique_id)
            early_death = self._early_deaths.pop(unique_id, None)
            if early_death is None:
                self._loaded[unique_id] = entry
        # The event first: logging goes to /rosout too, a DDS publish of its
        # own (0.6-0.9 ms inside the container, measured, when it came first).
        if args.drop_loaded_event:
            self._log.warning(
                f"not publishing LOADED for unique_id {unique_id} (fault injection: {seams.DROP_LOADED_EVENT})"
            )
        else:
            self._publish(events.LOADED, entry)
        where = f", {hosted.where}" if hosted.where else ""
        self._log.info(
            f"Loaded {spec.plugin_name} as {hosted.full_node_name} (unique_id {unique_id}, pid {hosted.pid}{where})"
        )
        if early_death is not None:
            self._report_crash(entry, early_death)
        else:
            if self._restarts is None:  # else CRASHED says what the policy decided
                try:
                    self._host.arm_crashed(hosted, events.message(events.CRASHED, **self._node_fields(entry)))
                except Exception as exc:  # then its CRASHED goes out through Python
                    self._log.warning(f"unique_id {unique_id}: its CRASHED stays Python's: {type(exc).__name__}: {exc}")
            # Its callbacks start now, not while the event and the log line
            # above were competing with them for the GIL.
            self._host.run(hosted)
        response.success = True
        response.full_node_name = hosted.full_node_name
        response.unique_id = unique_id
        return response

    def _on_unload_node(self, request: UnloadNode.Request, response: UnloadNode.Response) -> UnloadNode.Response:
        return self._contained("UnloadNode", self._unload, request, response)

    def _unload(self, request: UnloadNode.Request, response: UnloadNode.Response) -> UnloadNode.Response:
        with self._lock:
            entry = self._loaded.get(request.unique_id)
            # A node whose death the host announced is gone (on_death follows).
            if entry is not None and self._host.disarm_crashed(entry.hosted):
                del self._loaded[request.unique_id]
            else:
                entry = None
        if entry is None:
            response.success = False
            response.error_message = f"No node found with unique_id: {request.unique_id}"
            self._log.warning(response.error_message)
            return response
        intra.get_bus().forget(request.unique_id)
        self._host.stop(entry.hosted)
        self._log.info(f"Unloaded {entry.hosted.full_node_name} (unique_id {entry.hosted.unique_id})")
        self._publish(events.UNLOADED, entry)
        response.success = True
        return response

    def _on_list_nodes(self, request: ListNodes.Request, response: ListNodes.Response) -> ListNodes.Response:
        return self._contained("ListNodes", self._list, request, response)

    def _list(self, request: ListNodes.Request, response: ListNodes.Response) -> ListNodes.Response:
        with self._lock:
            entries = [(uid, e) for uid, e in sorted(self._loaded.items()) if not self._host.crashed_claimed(e.hosted)]
        response.unique_ids = [uid for uid, _ in entries]
        response.full_node_names = [e.hosted.full_node_name for _, e in entries]
        return response

    # -- deaths (called by the host, from the core's listener thread) ----------

    def on_death(self, unique_id: int, death: NodeDeath) -> None:
        """A node's process died without being unloaded."""
        # First of all: publishers stop queueing to its subscriptions and
        # waking its (dead) executor.
        intra.get_bus().forget(unique_id)
        with self._lock:
            if unique_id in self._starting:
                self._early_deaths[unique_id] = death
                return
            entry = self._loaded.pop(unique_id, None)
            if entry is not None:
                self._died[unique_id] = entry
                while len(self._died) > DIED_KEPT:
                    self._died.popitem(last=False)
        if entry is not None:  # None: an unload got there first
            self._report_crash(entry, death)

    def _report_crash(self, entry: _Entry, death: NodeDeath) -> None:
        hosted = entry.hosted
        restart = None
        if self._restarts is not None and self._node.context.ok():
            restart = self._restarts.on_crash(entry.request, entry.lineage, uptime(hosted.start_time_ns))
        reason = death.reason if restart is None else f"{death.reason}; {restart.text}"
        # The event first: logging goes to /rosout too, a DDS publish of its
        # own. The host may have published it already (arm_crashed).
        if not death.claimed:
            self._publish(
                events.CRASHED,
                entry,
                error_message=reason,
                exit_signal=death.exit_signal,
                exit_code=death.exit_code,
                allocator_quarantined=death.allocator_quarantined,
            )
        # A clean exit after an outside SIGTERM (the container's process
        # group stopped) is no error; its CRASHED says how it ended all the
        # same. (Two calls: rclpy refuses one call site logging at two
        # severities.)
        who = f"{hosted.full_node_name} (unique_id {hosted.unique_id}, pid {death.pid})"
        if death.stopped:
            self._log.info(f"{who} ended: {reason}")
        else:
            self._log.error(f"{who} died: {reason}{memory_budget.at_death(death.memory)}")

    def reload(self, request: LoadNode.Request, lineage: Lineage) -> None:
        """The restart policy's callback: load ``request`` again."""
        resp = self._contained("restart", self._load, request, LoadNode.Response(), lineage)
        if not resp.success:
            self._log.error(f"restart of {lineage.name} failed: {resp.error_message}")

    # -- life cycle -----------------------------------------------------------

    def stopping(self) -> None:
        """The container is stopping: a LoadNode still waiting for its node is
        answered now (success=false), not when the node is built; a node
        built later is stopped (as after CONSTRUCT_WAIT_S)."""
        with self._lock:
            self._stopping = True
            self._built.notify_all()

    def wait_answered(self, timeout: float) -> int:
        """After ``stopping``: wait for the requests in flight to be
        answered, at most ``timeout``; how many were not."""
        return self._unanswered.wait(timeout)

    def close(self) -> None:
        """Stop every node (container shutdown); no events, the context is gone."""
        if self._restarts is not None:
            self._restarts.cancel_all()
        with self._lock:
            entries, self._loaded = list(self._loaded.values()), {}
            for e in entries:  # their deaths from here on are no crashes
                self._host.disarm_crashed(e.hosted)
        for uid in [e.hosted.unique_id for e in entries]:
            intra.get_bus().forget(uid)
        self._host.close([e.hosted for e in entries])
        self._builders.shutdown(wait=False, cancel_futures=True)

    # -- helpers --------------------------------------------------------------

    def _start(self, unique_id: int, cls: type[Node], args: NodeArguments) -> Hosted:
        """host.start on a thread of its own, waited for at most
        CONSTRUCT_WAIT_S. A start that finishes after that is undone."""
        # box["late"] is set by whichever comes first, under the lock: the
        # start's end (False) or the load giving up (True).
        box: dict = {}

        def build() -> None:
            try:
                box["hosted"] = self._host.start(unique_id, cls, args)
            except BaseException as exc:
                box["error"] = exc
            with self._lock:
                late = box.setdefault("late", False)
                self._built.notify_all()
            if late and "hosted" in box:
                self._log.warning(f"unique_id {unique_id}: built after its LoadNode gave up; stopping it")
                self._host.stop(box["hosted"])

        self._builders.submit(build)
        with self._lock:
            self._built.wait_for(lambda: "late" in box or self._stopping, self.CONSTRUCT_WAIT_S)
            late = box.setdefault("late", True)
        if late:
            if self._stopping:
                raise LoadError("the container is stopping")
            raise LoadError(f"the node was not constructed within {self.CONSTRUCT_WAIT_S:g} s")
        if "error" in box:
            raise box["error"]
        return box["hosted"]

    def _take_id(self) -> int:
        with self._lock:
            unique_id, self._next_id = self._next_id, self._next_id + 1
            self._starting.add(unique_id)
        return unique_id

    def _load_failed(
        self, request: LoadNode.Request, response: LoadNode.Response, message: str, log_detail: str = ""
    ) -> LoadNode.Response:
        message = shown(message)
        # The detail is for the log only: clients get upstream's answer as is.
        detail = f" ({shown(log_detail, 1500)})" if log_detail else ""
        self._log.error(f"Failed to load component: {message}{detail}")
        self._events.publish(
            events.LOAD_FAILED,
            package_name=shown(request.package_name, 256),
            plugin_name=shown(request.plugin_name, 256),
            error_message=message,
        )
        response.success = False
        response.error_message = message
        response.full_node_name = ""
        response.unique_id = 0
        return response

    def _figures(self) -> list[tuple[str, int, int, tuple[int, int] | None]]:
        """Each loaded node's name, unique_id, pid and memory, for /diagnostics."""
        with self._lock:
            running = [entry.hosted for entry in self._loaded.values()]
        return [(h.full_node_name, h.unique_id, h.pid, self._host.memory(h)) for h in running]

    def publish_repairs(self) -> None:
        for repair in repairs.drain():
            with self._lock:  # most are repairs of what a dead node left
                entry = self._loaded.get(repair.unique_id) or self._died.get(repair.unique_id)
            names: dict[str, Any] = {}
            if entry is not None:
                names = {
                    "full_node_name": entry.hosted.full_node_name,
                    "package_name": entry.spec.package_name,
                    "plugin_name": entry.spec.plugin_name,
                    "pid": entry.hosted.pid,
                }
            self._events.publish(
                events.REPAIRED,
                unique_id=repair.unique_id,
                error_message=repair.detail,
                repaired_state=repair.state,
                stamp_ns=repair.stamp_ns,
                **names,
            )

    def _publish(self, event_type: int, entry: _Entry, **extra: Unpack[_CrashFields]) -> None:
        self._events.publish(event_type, **self._node_fields(entry), **extra)

    @staticmethod
    def _node_fields(entry: _Entry) -> dict[str, Any]:
        """What every event of a loaded node says of it."""
        hosted = entry.hosted
        return {
            "unique_id": hosted.unique_id,
            "full_node_name": hosted.full_node_name,
            "package_name": entry.spec.package_name,
            "plugin_name": entry.spec.plugin_name,
            "pid": hosted.pid,
            "start_time_ns": hosted.start_time_ns,
        }
