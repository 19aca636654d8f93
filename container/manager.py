"""The component manager: LoadNode / UnloadNode / ListNodes and their events.

It owns the table of loaded nodes and the unique-id counter; it validates a
request, asks the host to start or stop a node, and publishes what happened.
Its behaviour follows rclcpp_components' ComponentManager: ids start at 1 and
are never reused (a load that fails after an id was taken still uses it up),
a failed load answers unique_id 0 and an empty full_node_name.

Deaths come from the host (isolated mode), on its monitor's thread: the node
leaves the table, a CRASHED event goes out, and with a restart policy the
same request is loaded again after a backoff.
"""
from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass

from composition_interfaces.srv import ListNodes, LoadNode, UnloadNode

from . import events, intra, options, registry
from .events import EventPublisher
from .hosting import Hosted
from .options import LoadError
from .restart import Lineage, uptime


@dataclass
class _Entry:
    hosted: Hosted
    spec: registry.ComponentSpec
    request: LoadNode.Request
    lineage: Lineage


class ComponentManager:
    # How long a LoadNode may block the executor while a node is built.
    LOAD_ALLOWANCE_S = 70.0

    def __init__(self, node, host, *, logger=None):
        self._node = node
        self._host = host
        self._log = logger or node.get_logger()
        self._events = EventPublisher(node)
        self._lock = threading.Lock()       # guards the fields below
        self._next_id = 1
        self._loaded: dict[int, _Entry] = {}
        self._starting: set[int] = set()    # ids whose host.start() is running
        self._early_deaths: dict[int, object] = {}   # deaths seen while starting
        self.watchdog = None                # set by the command line when it runs one
        self.restart_policy = None          # likewise (container.restart.RestartPolicy)
        # The intra-process bus is container-owned: made here, before any child.
        intra.get_bus()
        node.create_service(LoadNode, "~/_container/load_node", self._on_load_node)
        node.create_service(UnloadNode, "~/_container/unload_node", self._on_unload_node)
        node.create_service(ListNodes, "~/_container/list_nodes", self._on_list_nodes)

    # -- services -------------------------------------------------------------

    def _on_load_node(self, request, response):
        return self._load(request, response, None)

    def _load(self, request, response, lineage: Lineage | None):
        try:
            spec = registry.find(request.package_name, request.plugin_name)
            args = options.from_request(request)
            cls = spec.load_class()
        except LoadError as exc:
            return self._load_failed(request, response, str(exc))
        unique_id = self._take_id()
        try:
            with self.watchdog.allow(self.LOAD_ALLOWANCE_S) if self.watchdog else contextlib.nullcontext():
                hosted = self._host.start(unique_id, cls, args)
        except LoadError as exc:
            intra.get_bus().forget(unique_id)   # what a failed constructor registered
            with self._lock:
                self._starting.discard(unique_id)
            return self._load_failed(request, response, str(exc))
        entry = _Entry(hosted, spec, request, lineage or Lineage(hosted.full_node_name))
        with self._lock:
            self._starting.discard(unique_id)
            early_death = self._early_deaths.pop(unique_id, None)
            if early_death is None:
                self._loaded[unique_id] = entry
        self._log.info(
            f"Loaded {spec.plugin_name} as {hosted.full_node_name} "
            f"(unique_id {unique_id}, pid {hosted.pid})"
        )
        if args.drop_loaded_event:
            self._log.warning(
                f"not publishing LOADED for unique_id {unique_id} "
                f"(fault injection: {options.DROP_LOADED_EVENT})")
        else:
            self._publish(events.LOADED, entry)
        if early_death is not None:
            self._report_crash(entry, early_death)
        response.success = True
        response.full_node_name = hosted.full_node_name
        response.unique_id = unique_id
        return response

    def _on_unload_node(self, request, response):
        with self._lock:
            entry = self._loaded.pop(request.unique_id, None)
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

    def _on_list_nodes(self, request, response):
        with self._lock:
            entries = sorted(self._loaded.items())
        response.unique_ids = [uid for uid, _ in entries]
        response.full_node_names = [e.hosted.full_node_name for _, e in entries]
        return response

    # -- deaths (called by the host, from its monitor's thread) -----------------

    def on_death(self, unique_id: int, death) -> None:
        """A node's process died without being unloaded."""
        # First of all: publishers stop queueing to its subscriptions and
        # waking its (dead) executor.
        intra.get_bus().forget(unique_id)
        with self._lock:
            if unique_id in self._starting:
                self._early_deaths[unique_id] = death
                return
            entry = self._loaded.pop(unique_id, None)
        if entry is not None:   # None: an unload got there first
            self._report_crash(entry, death)

    def _report_crash(self, entry: _Entry, death) -> None:
        hosted = entry.hosted
        # The event first: logging goes to /rosout too, a DDS publish of its own.
        self._publish(
            events.CRASHED, entry,
            error_message=death.reason,
            exit_signal=death.exit_signal,
            exit_code=death.exit_code,
            allocator_quarantined=death.allocator_quarantined,
        )
        self._log.error(
            f"{hosted.full_node_name} (unique_id {hosted.unique_id}, pid {death.pid}) "
            f"died: {death.reason}"
        )
        if self.restart_policy is not None and self._node.context.ok():
            delay = self.restart_policy.on_crash(entry.request, entry.lineage, uptime(hosted.start_time_ns))
            self._log.warning(
                f"restarting {entry.lineage.name} in {delay:g} s "
                f"(restart {entry.lineage.restarts})"
            )

    def reload(self, request, lineage: Lineage) -> None:
        """The restart policy's callback: load ``request`` again."""
        resp = self._load(request, LoadNode.Response(), lineage)
        if not resp.success:
            self._log.error(f"restart of {lineage.name} failed: {resp.error_message}")

    # -- life cycle -----------------------------------------------------------

    def close(self) -> None:
        """Stop every node (container shutdown); no events, the context is gone."""
        if self.restart_policy is not None:
            self.restart_policy.cancel_all()
        with self._lock:
            entries, self._loaded = list(self._loaded.values()), {}
        for uid in [e.hosted.unique_id for e in entries]:
            intra.get_bus().forget(uid)
        self._host.close([e.hosted for e in entries])

    # -- helpers --------------------------------------------------------------

    def _take_id(self) -> int:
        with self._lock:
            unique_id, self._next_id = self._next_id, self._next_id + 1
            self._starting.add(unique_id)
        return unique_id

    def _load_failed(self, request, response, message: str):
        self._log.error(f"Failed to load component: {message}")
        self._events.publish(
            events.LOAD_FAILED,
            package_name=request.package_name,
            plugin_name=request.plugin_name,
            error_message=message,
        )
        response.success = False
        response.error_message = message
        response.full_node_name = ""
        response.unique_id = 0
        return response

    def _publish(self, event_type, entry: _Entry, **extra) -> None:
        hosted = entry.hosted
        self._events.publish(
            event_type,
            unique_id=hosted.unique_id,
            full_node_name=hosted.full_node_name,
            package_name=entry.spec.package_name,
            plugin_name=entry.spec.plugin_name,
            pid=hosted.pid,
            start_time_ns=hosted.start_time_ns,
            **extra,
        )
