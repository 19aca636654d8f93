"""Where a loaded node's callbacks run.

The manager decides *what* is loaded; a host decides *where* it runs. The
thread host spins every node on the container's own executor (single- or
multi-threaded). The isolated host (``container.isolated.host``) gives each
node its own clone(CLONE_VM) child. Both are a :class:`Host`.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from rclpy.node import Node

from . import construction
from .memory_budget import MEMORY_LIMIT, OOM_SCORE_ADJ
from .options import CPU_QUOTA, PROFILE, LoadError, NodeArguments

if TYPE_CHECKING:
    from cloneguard_interfaces.msg import ComponentEvent
    from rclpy.context import Context
    from rclpy.impl.rcutils_logger import RcutilsLogger

    from .events import EventPublisher
    from .executors import NodeWork


@dataclass
class Hosted:
    """A node that a host is running."""

    unique_id: int
    full_node_name: str
    pid: int
    start_time_ns: int
    node: Node | None = None  # the node object, where the container holds it
    detail: Any = field(default=None, repr=False)  # host-specific state
    where: str = ""  # how the host runs it, for the load's log line ("profile shared")


@dataclass(frozen=True)
class NodeDeath:
    """What the manager is told when a node's process dies on its own."""

    pid: int
    exit_signal: int
    exit_code: int
    reason: str
    allocator_quarantined: bool = False
    claimed: bool = False  # the host published its CRASHED event (Host.arm_crashed)
    # It exited with status 0 after an outside SIGTERM or SIGINT (the
    # container's process group being stopped, say): a clean stop, no crash.
    stopped: bool = False
    # (bytes in use, budget in bytes, 0: none) at its death, as the
    # allocator guard counted them; None where nothing counts them.
    memory: tuple[int, int] | None = None


class Host(Protocol):
    """What the manager asks of a host."""

    def start(self, unique_id: int, cls: type[Node], args: NodeArguments) -> Hosted:
        """Build the node, ready to run; raise ``LoadError`` if it cannot be."""

    def run(self, hosted: Hosted) -> None:
        """Let its callbacks run (the manager calls it once it has published
        the load, so that they do not compete with that for the GIL)."""

    def stop(self, hosted: Hosted) -> None:
        """Stop running it and destroy it."""

    def close(self, hosted_nodes: Sequence[Hosted]) -> None:
        """Stop every one of ``hosted_nodes`` and what the host keeps of its
        own (container shutdown)."""

    def report_deaths_to(self, on_death: Callable[[int, NodeDeath], None]) -> None:
        """Where a node the host loses on its own (a child that dies) is
        reported: ``on_death(unique_id, death)``."""

    def publish_crashed_with(self, events: EventPublisher) -> None:
        """A host that can may publish a node's CRASHED event itself, on the
        manager's event publisher (``events``), as soon as the node dies."""

    def arm_crashed(self, hosted: Hosted, event: ComponentEvent) -> None:
        """From now on it does so for this node, publishing ``event`` (its
        CRASHED with every field known at load) completed with the death;
        ``on_death`` then says it did (``death.claimed``)."""

    def disarm_crashed(self, hosted: Hosted) -> bool:
        """Take that back: False if too late (the node is dead, its CRASHED
        claimed by the host)."""

    def crashed_claimed(self, hosted: Hosted) -> bool:
        """Whether the host has claimed the node's death (on_death may not
        have come yet)."""

    def memory(self, hosted: Hosted) -> tuple[int, int] | None:
        """(bytes in use, budget) of the node, None where nothing counts it."""


class ThreadHost:
    """Every node on the container's own executor, as upstream's containers."""

    # How long an unload waits for a callback of the node that is running
    # (a long action goal, say) before destroying the node under it.
    RETIRE_WAIT_S = 2.0

    def __init__(self, executor: NodeWork, context: Context, log: RcutilsLogger) -> None:
        self._executor = executor
        self._context = context
        self._log = log
        # unique_id -> "built" / "running" / "stopped": an UnloadNode sent
        # on seeing LOADED can come before run() (the event goes out first).
        self._lock = threading.Lock()
        self._states: dict[int, str] = {}

    def start(self, unique_id: int, cls: type[Node], args: NodeArguments) -> Hosted:
        if args.cpu_quota is not None:
            raise LoadError(f"a CPU quota ({CPU_QUOTA}) needs an isolated container started with --cgroups")
        if args.memory_limit:
            raise LoadError(
                f"a memory budget ({MEMORY_LIMIT}) needs an isolated container: in thread mode every node "
                "is the container's one process, whose only budget is the whole container's (a memory cgroup)"
            )
        if args.oom_score_adj is not None:
            raise LoadError(
                f"an out-of-memory score ({OOM_SCORE_ADJ}) needs an isolated container: in thread mode "
                "no node can be ended alone"
            )
        if args.profile is not None:
            raise LoadError(f"a participant profile ({PROFILE}) needs an isolated container (--isolated)")
        start = time.time_ns()
        node = construction.construct(cls, args, self._context, unique_id)
        with self._lock:
            self._states[unique_id] = "built"
        return Hosted(unique_id, node.get_fully_qualified_name(), os.getpid(), start, node)

    def run(self, hosted: Hosted) -> None:
        """Let a started node's callbacks run: it joins the container's
        executor (after the LoadNode's LOADED event, as in isolated mode),
        unless it was stopped first."""
        with self._lock:
            if self._states.get(hosted.unique_id) != "built":
                return
            self._states[hosted.unique_id] = "running"
            self._executor.add_node(hosted.node)  # type: ignore[arg-type]  # thread mode holds every node it built

    def stop(self, hosted: Hosted) -> None:
        with self._lock:
            was = self._states.pop(hosted.unique_id, None)
        node = hosted.node
        assert node is not None, "thread mode holds every node it built"
        if was == "running":
            self._executor.remove_node(node)
            if not self._executor.retire(node, self.RETIRE_WAIT_S):
                self._log.warning(
                    f"{hosted.full_node_name}: a callback of it still ran {self.RETIRE_WAIT_S:g} s after its "
                    "unload began; it is destroyed under that callback"
                )
            self._quiesce()
        construction.destroy(node)

    def _quiesce(self, timeout: float = 2.0) -> None:
        """Wait until the executor has been round its loop once more: a wait
        it was in when the node was removed still held the node's entities,
        and destroying a node while they are in use leaks them (rclpy 7.1:
        ~0.17 MiB of malloc'd memory per load/unload, measured)."""
        if self._executor._is_shutdown:
            return
        turned = threading.Event()
        self._executor.create_task(turned.set)
        self._executor.wake()
        turned.wait(timeout)

    def report_deaths_to(self, on_death: Callable[[int, NodeDeath], None]) -> None:
        """Nothing to report: a node on the container's executor dies only
        with the container."""

    def publish_crashed_with(self, events: EventPublisher) -> None:
        """No deaths, nothing to announce (see report_deaths_to)."""

    def arm_crashed(self, hosted: Hosted, event: ComponentEvent) -> None:
        pass

    def disarm_crashed(self, hosted: Hosted) -> bool:
        return True

    def crashed_claimed(self, hosted: Hosted) -> bool:
        return False

    def memory(self, hosted: Hosted) -> tuple[int, int] | None:
        """Nothing counts a node's memory in the container's one process."""
        return None

    def close(self, hosted_nodes: Sequence[Hosted]) -> None:
        for hosted in hosted_nodes:
            self.stop(hosted)


_THREAD_HOST_IS_A_HOST: type[Host] = ThreadHost  # mypy holds it to the protocol
