"""What a launcher believes about each node it asked a container to load.

States: Loading -> Loaded / Failed, then Loaded -> Unloaded / Crashed.
They change on LoadNode answers and ComponentEvents only, with one fallback:
a node still Loading ``fallback_s`` (10 s) after its LoadNode succeeded, with
a known unique_id, because its LOADED event never came, is promoted to Loaded
with a warning, but only if ListNodes confirms it is there. A node that is
not listed (it was killed after the answer and its events were lost) is
marked Failed, never Loaded. A LOADED event that arrives after the promotion
changes nothing.
"""

from __future__ import annotations

import enum
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from cloneguard_interfaces.msg import ComponentEvent

from .client import ContainerClient, HarnessTimeout

if TYPE_CHECKING:
    from typing import Unpack

    from .client import LoadFields

LOADING_FALLBACK_S = 10.0


class State(enum.Enum):
    LOADING = "Loading"
    LOADED = "Loaded"
    FAILED = "Failed"
    UNLOADED = "Unloaded"
    CRASHED = "Crashed"


FINAL = {State.FAILED, State.UNLOADED, State.CRASHED}


@dataclass
class TrackedNode:
    package_name: str
    plugin_name: str
    requested_name: str
    state: State = State.LOADING
    unique_id: int = 0
    full_node_name: str = ""
    pid: int = 0
    answered_at: float | None = None  # monotonic time of the LoadNode answer
    error: str = ""
    warnings: list[str] = field(default_factory=list)
    history: list[tuple[float, State, str]] = field(default_factory=list)
    crash: ComponentEvent | None = None


class NodeTracker:
    def __init__(self, client: ContainerClient, *, fallback_s: float = LOADING_FALLBACK_S):
        self._client = client
        self.fallback_s = fallback_s
        self._cond = threading.Condition()
        self._nodes: list[TrackedNode] = []
        self._by_id: dict[int, TrackedNode] = {}
        self._early: dict[int, list[ComponentEvent]] = {}  # events before the answer
        self._stopped = False
        client.events.add_listener(self._on_event)
        self._fallback = threading.Thread(target=self._fallback_loop, name="tracker-fallback", daemon=True)
        self._fallback.start()

    # -- what the launcher does ---------------------------------------------------

    def load(
        self, package_name: str, plugin_name: str, *, timeout: float = 30.0, **fields: Unpack[LoadFields]
    ) -> TrackedNode:
        node = TrackedNode(package_name, plugin_name, fields.get("node_name", ""))
        with self._cond:
            self._nodes.append(node)
            self._set(node, State.LOADING, "LoadNode sent")
        try:
            resp = self._client.load(package_name, plugin_name, timeout=timeout, **fields)
        except HarnessTimeout as exc:
            with self._cond:
                self._set(node, State.FAILED, f"no LoadNode answer: {exc}")
            return node
        with self._cond:
            node.answered_at = time.monotonic()
            if not resp.success:
                node.error = resp.error_message
                self._set(node, State.FAILED, f"LoadNode failed: {resp.error_message}")
                return node
            node.unique_id = resp.unique_id
            node.full_node_name = resp.full_node_name
            self._by_id[resp.unique_id] = node
            for ev in self._early.pop(resp.unique_id, []):
                self._apply(node, ev)
            self._cond.notify_all()
        return node

    def unload(self, node: TrackedNode, *, timeout: float = 10.0) -> bool:
        resp = self._client.unload(node.unique_id, timeout=timeout)
        if not resp.success:
            node.warnings.append(f"UnloadNode failed: {resp.error_message}")
        return resp.success

    def nodes(self) -> list[TrackedNode]:
        with self._cond:
            return list(self._nodes)

    def wait_state(self, node: TrackedNode, states: State | Iterable[State], timeout: float) -> State:
        wanted = {states} if isinstance(states, State) else set(states)
        with self._cond:
            if not self._cond.wait_for(lambda: node.state in wanted, timeout):
                raise HarnessTimeout(
                    f"{node.full_node_name or node.requested_name or node.plugin_name} is "
                    f"{node.state.value}, not {'/'.join(s.value for s in wanted)}, after {timeout:.1f} s"
                )
            return node.state

    def close(self) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        self._client.events.remove_listener(self._on_event)
        self._fallback.join()

    # -- events -------------------------------------------------------------------

    def _on_event(self, ev: ComponentEvent) -> None:
        if ev.event_type == ComponentEvent.LOAD_FAILED or ev.unique_id == 0:
            return  # the LoadNode answer already said so
        with self._cond:
            node = self._by_id.get(ev.unique_id)
            if node is None:
                self._early.setdefault(ev.unique_id, []).append(ev)
                return
            self._apply(node, ev)

    def _apply(self, node: TrackedNode, ev: ComponentEvent) -> None:
        if ev.pid:
            node.pid = ev.pid
        if ev.event_type == ComponentEvent.LOADED:
            if node.state == State.LOADING:
                self._set(node, State.LOADED, "LOADED event")
            else:
                node.history.append((time.monotonic(), node.state, f"late LOADED event ignored ({node.state.value})"))
        elif ev.event_type == ComponentEvent.CRASHED:
            node.crash = ev
            self._set(node, State.CRASHED, f"CRASHED event: {ev.error_message}")
        elif ev.event_type == ComponentEvent.UNLOADED:
            self._set(node, State.UNLOADED, "UNLOADED event")

    def _set(self, node: TrackedNode, state: State, why: str) -> None:
        node.state = state
        node.history.append((time.monotonic(), state, why))
        self._cond.notify_all()

    # -- the 10-second fallback ---------------------------------------------------------

    def _overdue(self, now: float) -> list[TrackedNode]:
        return [
            n
            for n in self._nodes
            if n.state == State.LOADING
            and n.unique_id
            and n.answered_at is not None
            and now - n.answered_at >= self.fallback_s
        ]

    def _next_deadline(self) -> float | None:
        waiting = [
            n.answered_at + self.fallback_s
            for n in self._nodes
            if n.state == State.LOADING and n.unique_id and n.answered_at is not None
        ]
        return min(waiting) if waiting else None

    def _fallback_loop(self) -> None:
        while True:
            with self._cond:
                while not self._stopped:
                    deadline = self._next_deadline()
                    now = time.monotonic()
                    if deadline is not None and deadline <= now:
                        break
                    self._cond.wait(None if deadline is None else deadline - now)
                if self._stopped:
                    return
                overdue = self._overdue(time.monotonic())
            try:
                listed = {uid for uid, _name in self._client.list(timeout=5.0)}
            except HarnessTimeout as exc:
                listed, why = set(), f"ListNodes failed ({exc})"
            else:
                why = "not in ListNodes"
            with self._cond:
                for node in overdue:
                    if node.state != State.LOADING:
                        continue  # an event got there while we asked
                    if node.unique_id in listed:
                        msg = (
                            f"no LOADED event {self.fallback_s:.0f} s after LoadNode succeeded; "
                            "promoted to Loaded (ListNodes confirms it)"
                        )
                        node.warnings.append(msg)
                        self._set(node, State.LOADED, msg)
                    else:
                        msg = f"no LOADED event {self.fallback_s:.0f} s after LoadNode succeeded and {why}"
                        node.warnings.append(msg)
                        self._set(node, State.FAILED, msg)
