"""The isolated host: each loaded node's executor in its own clone(CLONE_VM) child.

Two participant profiles say where a node is built:

``shared`` (default)
    The child builds the node on the container's Context (one DDS
    participant for all) and spins it. A child that dies inside DDS can
    leave the container's participant locked (the lock doctor repairs what
    a waiter meets); a constructor that crashes ends only its child.
``per-node``
    The child creates its own rclpy Context (its own DDS participant) and
    builds the node in it. A child that dies takes only its own participant's
    threads and locks with it.

The container's ``--profile`` is every load's unless the load asks for
one (extra argument ``cloneguard.profile``): a container can give most of
its nodes the shared profile's cost and the few that need it a participant
of their own, or the reverse.

Either way the child runs one SingleThreadedExecutor, once the manager has
announced the load (``run``: until then the child waits at its gate, off
the GIL). Per-node children are taken from the warm spare when one can serve
the load (spare.py). Stopping a node: cancel (stop flag + executor wake-up),
SIGTERM, up to 500 ms, then SIGKILL.

After a child dies on its own the node's objects are not destroyed: the dead
child may have held locks inside them (rclpy, Fast DDS), and destroying them
could block the container on a lock nobody will release. They are kept,
counted and logged, a bounded leak per crash.
"""

from __future__ import annotations

import ctypes
import os
import select
import signal
import threading
import time
import traceback
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rclpy
from rclpy.context import Context
from rclpy.executors import (
    ConditionReachedException,
    ExternalShutdownException,
    ShutdownException,
    SingleThreadedExecutor,
    TimeoutException,
)
from rclpy.signals import SignalHandlerOptions

from .. import construction, intra, processes, repairs
from ..hosting import Host, Hosted, NodeDeath
from ..memory_budget import MEMORY_LIMIT
from ..options import CPU_QUOTA, LoadError
from ..robust import RobustMutex
from . import listener_wait, mutex_reports, reclaim
from .board import ProgressBoard
from .core import CloneCore, Death, Mitigations, StopRequested, stop_requested, wait_for_go
from .core_dumps import path_for as core_dump_path
from .core_dumps import size as core_dump_size
from .core_dumps import tools as core_dump_tools
from .core_events import MutexReport
from .memory_watch import MemoryLimit
from .placeholder import held_context, release_context
from .profiles import DEFAULT, PROFILES, SHARED, ProfileRule
from .profiles import choose as choose_profile
from .spare import Spare, serves, spare_target

if TYPE_CHECKING:
    from collections.abc import Callable

    from cloneguard_interfaces.msg import ComponentEvent
    from rclpy.impl.rcutils_logger import RcutilsLogger
    from rclpy.node import Node

    from ..events import EventPublisher
    from ..options import NodeArguments
    from .board import BoardRepair
    from .cgroups import NodeCgroups
    from .core import Child
    from .core_events import CoreEvent
    from .placeholder import Placeholder

STOP_TIMEOUT_S = 0.5
CONSTRUCT_TIMEOUT_S = 60.0
# After a failed construction the child tears its half-made node and DDS
# participant down and ends; if it does not (a thread that will not stop)
# within this, it is killed.
FAILED_EXIT_TIMEOUT_S = 5.0

# The one-byte words a child (or the monitor) posts on a handoff.
READY, FAILED, DIED = b"R", b"F", b"D"


class _Handoff:
    """One-shot word from a child to the thread waiting for it: a pipe, so a
    child that dies half-way can never leave a lock behind for the waiter.
    Words are one byte and the waiter reads one: the child's word and the
    monitor's DIED (it exits right after posting) never run together."""

    def __init__(self) -> None:
        self._r, self._w = os.pipe2(os.O_CLOEXEC)
        self.closed = False

    def post(self, word: bytes) -> None:
        os.write(self._w, word)

    def wait(self, timeout: float) -> bytes | None:
        # poll, not select: every crashed per-node child leaves its
        # participant's sockets open (~9 fds), and after ~110 crashes this
        # pipe's fds are past select's FD_SETSIZE (1024).
        waiter = select.poll()
        waiter.register(self._r, select.POLLIN)
        ready = waiter.poll(None if timeout is None else timeout * 1000)
        return os.read(self._r, 1) if ready else None

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            for fd in (self._r, self._w):
                os.close(fd)


@dataclass
class _NodeProcess:
    unique_id: int
    profile: str
    # starting -> running -> stopping -> gone; starting or running -> dead (it died on
    # its own) -> gone; starting -> gone (its start failed)
    state: str = "starting"
    # Set as the start goes on (Any: each is None only until then).
    child: Any = None  # core.Child
    node: Any = None  # rclpy Node
    executor: Any = None  # SingleThreadedExecutor
    full_name: str = ""
    slot: int = -1  # this node's slot on the progress board
    start_ns: int = 0
    stop_guard: Any = None  # triggered to wake the child's spin loop
    cgroup: Any = None  # NodeCgroup, with --cgroups
    error: str = ""  # why construction failed in the child
    aborted: str = ""  # why the container aborted it (node watchdog)
    stop_signal: int | None = None  # an outside SIGTERM/SIGINT it was sent
    death: Death | None = None
    handoff: _Handoff = field(default_factory=_Handoff)
    kept: list = field(default_factory=list)  # dead-only objects held for good (reclaim.py)


class IsolatedHost:
    def __init__(
        self,
        context: Context,
        *,
        profile: str = DEFAULT,
        logger: RcutilsLogger,
        cgroups: NodeCgroups | None = None,
        mitigations: Mitigations | None = None,
        warm_spare: bool = True,
        container_argv: Sequence[str] = (),
        core_dumps: Path | None = None,
        profile_rules: Sequence[ProfileRule] = (),
        stop_signal: int = 0,
        node_memory_limit: int = 0,
        memory_watch: tuple[MemoryLimit, int] | None = None,
    ) -> None:
        if profile not in PROFILES:
            raise ValueError(f"unknown profile {profile!r}; expected one of {PROFILES}")
        self._context = context
        self.profile = profile
        self.profile_rules = list(profile_rules)  # --profile-for, before the default
        self.node_memory_limit = node_memory_limit  # bytes, 0: none (memory_budget.py)
        self._on_death: Callable[[int, NodeDeath], None] | None = None  # report_deaths_to
        self._herald_handle = None  # publish_crashed_with: the publisher, in use
        self._log = logger
        # The container's command line: the global ROS arguments a node built
        # with forward_global_arguments gets on its own Context (per-node).
        self._container_argv = list(container_argv)
        # Any node may be built on the container's Context (the shared
        # profile's, or a load asking for it: options.PROFILE), whatever
        # the default.
        _robust_context_lock(context, logger)
        self._lock = threading.Lock()
        self._by_pid: dict[int, _NodeProcess] = {}
        self.leaked: list[_NodeProcess] = []
        # One thread gives dead nodes' memory back (reclaim.py): examining a
        # big leak takes seconds, holding the GIL in turns.
        self._reclaimer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="cloneguard-reclaim")
        self.board = ProgressBoard(on_repair=self._board_repaired)
        self.cgroups = cgroups  # NodeCgroups, or None: no per-node cgroups
        self.mitigations = mitigations or Mitigations()
        self._core_dumps = core_dumps  # the directory, or None: no dumps
        self._core = CloneCore(
            on_event=self._on_core_event,
            mitigations=self.mitigations,
            stop_signal=stop_signal,  # the test rig's stop points (seams.stop_signal), 0: none
            dump_tools=core_dump_tools() if core_dumps is not None else None,
            memory_watch=memory_watch,  # (what the container may use, margin): memory_watch.py
        )
        _say_monitor_priority(self._core.monitor_realtime(), logger)
        listener_wait.bound(logger)  # before any node's participant is deleted
        # The per-node profile's next process, made ahead (spare.py); not
        # with cgroups, where each node's process is born in its own.
        self._spare: Spare | None = None
        self._closing = False
        self.keeps_spare = warm_spare and profile != SHARED and cgroups is None
        self._spare_maker = None
        if self.keeps_spare:
            self._spare_maker = ThreadPoolExecutor(1, thread_name_prefix="cloneguard-spare")
            self._want_spare()

    # -- host interface ---------------------------------------------------------

    def report_deaths_to(self, on_death: Callable[[int, NodeDeath], None]) -> None:
        """Where a node's death goes (the manager's on_death); said once."""
        if self._on_death is not None:
            raise RuntimeError("deaths are already reported elsewhere")
        self._on_death = on_death

    def publish_crashed_with(self, events: EventPublisher) -> None:
        """Let the core publish a node's CRASHED event itself, on ``events``'
        publisher (herald.c: a thread of its own, no Python on the way), for
        the nodes ``arm_crashed`` arms. The publisher stays in use, so
        that rclpy cannot destroy it, until close() has stopped the herald."""
        handle = events.handle
        handle.__enter__()
        try:
            self._core.start_herald(*events.publish_from_c())
        except Exception as exc:  # the container goes on: Python publishes them all
            handle.__exit__(None, None, None)
            self._log.warning(f"CRASHED events go out through Python only: {type(exc).__name__}: {exc}")
            return
        self._herald_handle = handle

    def arm_crashed(self, hosted: Hosted, event: ComponentEvent) -> None:
        """Should the node's process die from now on, the core publishes
        ``event``, its CRASHED, completed with the death (``publish_crashed_with``),
        and the manager hears of the death with ``claimed`` set. Undone by
        ``disarm_crashed``."""
        proc = hosted.detail
        with self._lock:  # against a stop or an abort changing its state
            if self._herald_handle is None or proc.state != "running":
                return
            self._core.arm_crashed(proc.child, event)

    def disarm_crashed(self, hosted: Hosted) -> bool:
        """Take the node's CRASHED event back from the core: True if its
        death, should it come, is the caller's to report; False if the core
        has announced it (the node is dead; on_death follows)."""
        return self._core.disarm_crashed(hosted.detail.child)

    def crashed_claimed(self, hosted: Hosted) -> bool:
        """The core has announced the node's death; on_death may not have
        been called yet."""
        return self._core.crashed_claimed(hosted.detail.child)

    def memory(self, hosted: Hosted) -> tuple[int, int] | None:
        """(bytes in use, budget in bytes, 0: none) of the node's process as
        the allocator guard counts them; None without the guard, or once
        the host has forgotten its process."""
        return self._memory_of(hosted.detail)

    def _memory_of(self, proc: _NodeProcess) -> tuple[int, int] | None:
        """What the guard counts of ``proc``, alive or dead (a dead one's
        slot keeps its count until the next process in its context starts)."""
        if proc.child is None:
            return None
        try:
            return self._core.memory(proc.child)
        except ValueError:  # released meanwhile
            return None

    def start(self, unique_id: int, cls: type[Node], args: NodeArguments) -> Hosted:
        if args.cpu_quota is not None and self.cgroups is None:
            raise LoadError(f"a CPU quota ({CPU_QUOTA}) needs a container started with --cgroups")
        if args.memory_limit and not self.mitigations.alloc_guard:
            raise LoadError(
                f"a memory budget ({MEMORY_LIMIT}) needs the allocator guard, which counts each node's "
                "memory: this container runs with --no-alloc-guard"
            )
        profile = args.profile or choose_profile(self.profile_rules, args.requested_name, args.plugin) or self.profile
        proc = _NodeProcess(unique_id, profile)
        try:
            self._start(proc, cls, args)
        except BaseException as exc:
            # Whatever was half made goes: the child, the container-built
            # node, the cgroup, the board slot, the handoff pipe.
            self._undo(proc)
            self._want_spare()  # it may have used the spare
            if isinstance(exc, LoadError):
                raise
            self._log.error(
                f"unique_id {unique_id}: starting its process failed:\n" + "".join(traceback.format_exception(exc))
            )
            raise LoadError(f"the node's process could not be started: {type(exc).__name__}: {exc}") from None
        with self._lock:
            # The handoff is closed under the lock that guards posting to it.
            proc.handoff.close()
            died = proc.death
            proc.state = "running" if died is None else "dead"
        processes.node_is(proc.child.pid, unique_id, proc.full_name)
        self._name_dump(proc.child, proc.full_name)
        hosted = Hosted(unique_id, proc.full_name, proc.child.pid, proc.start_ns, detail=proc,
                        where=f"profile {proc.profile}")  # fmt: skip
        if died is not None:  # died between construction and now
            self._crashed(proc, died)
        return hosted

    def _start(self, proc: _NodeProcess, cls: type[Node], args: NodeArguments) -> None:
        unique_id = proc.unique_id
        limit = self.node_memory_limit if args.memory_limit is None else args.memory_limit
        oom_score_adj = args.oom_score_adj or 0
        if args.use_intra_process_comms:
            # Its subscriptions are woken by a container thread, never by a
            # publisher's process (rclglue/waker.c); the manager's forget()
            # closes it.
            intra.get_bus().open_waker(unique_id)
        proc.slot = self.board.register(unique_id)
        proc.start_ns = time.time_ns()
        if proc.profile == SHARED:
            target = self._shared_target(proc, cls, args)
        else:
            target = self._fresh_target(proc, cls, args)
        if self.cgroups is not None:
            proc.cgroup = self.cgroups.create(unique_id, args.cpu_quota)
        with self._lock:
            # The spare is taken, or a child spawned, under the lock that
            # routes deaths: one that dies right away is this load's.
            spare = self._take_spare(args) if proc.profile != SHARED else None
            if spare is not None:
                spare.order = (proc, cls, args)
                proc.child = spare.child
            else:
                proc.child = self._core.spawn(target, cgroup_fd=proc.cgroup.fd if proc.cgroup else None)
            self._by_pid[proc.child.pid] = proc
            self._name_dump(proc.child, proc.full_name or args.requested_name or args.plugin)
            if limit:
                self._core.set_memory_limit(proc.child, limit)
            if oom_score_adj:
                self._core.set_oom_score_adj(proc.child, oom_score_adj)
            if spare is not None:
                self._core.go(proc.child)
        processes.node_is(proc.child.pid, unique_id, "")  # named for a dead lock holder; the name once built
        if proc.cgroup is not None:
            self.cgroups.attach(proc.cgroup, proc.child.pid)  # type: ignore[union-attr]  # with --cgroups only
        self._await_construction(proc)

    def _undo(self, proc: _NodeProcess) -> None:
        """Undo a start that failed part-way (each step best-effort, so that
        one failure does not keep the rest in place)."""
        steps = []
        if proc.child is not None and proc.state != "gone":
            steps.append(lambda: self._end_child(proc))
        if proc.cgroup is not None:
            steps.append(lambda: self.cgroups.remove(proc.cgroup))  # type: ignore[union-attr]  # with --cgroups only
        if proc.slot >= 0:
            steps.append(lambda: self.board.unregister(proc.unique_id))
        steps.append(lambda: proc.handoff.close())
        for step in steps:
            try:
                step()
            except Exception as exc:
                self._log.error(
                    f"unique_id {proc.unique_id}: clean-up after a failed start: {type(exc).__name__}: {exc}"
                )
        proc.cgroup = None

    @staticmethod
    def _destroy_built(proc: _NodeProcess) -> None:
        """A shared-profile node whose process ended cleanly: its executor,
        then it (a per-node process destroys its own, with its Context)."""
        proc.executor.shutdown()
        construction.destroy(proc.node)

    def _end_child(self, proc: _NodeProcess) -> None:
        """SIGKILL a child that was spawned for a start that failed; reap it;
        keep what it left (it may have held locks), give its context back."""
        self._core.kill(proc.child, signal.SIGKILL)
        self._core.wait(proc.child)
        with self._lock:
            self._by_pid.pop(proc.child.pid, None)
            proc.state = "gone"
        self._core.abandon(proc.child)

    def run(self, hosted: Hosted) -> None:
        """Let a started node's process run its callbacks. Until then it
        waits off the GIL, so that the container announces the load without
        competing with the node's first executor iteration. Unload, shutdown
        and stop signals let it go too, to stop. Then a new spare is made."""
        proc = hosted.detail
        with self._lock:
            if proc.state == "running":
                self._core.go(proc.child)
        self._want_spare()

    def stop(self, hosted: Hosted) -> None:
        self._stop_all([hosted.detail])

    def close(self, hosted_nodes: Sequence[Hosted]) -> None:
        with self._lock:
            self._closing = True
        # Before the nodes stop: no CRASHED for them.
        if not self._core.stop_herald():
            # Its publisher stays in use: rclpy must never destroy it under it.
            self._log.error(
                "the core's herald thread is stuck publishing a CRASHED event (a dead node may hold "
                "a lock of Fast DDS's); it is left as it is"
            )
        elif self._herald_handle is not None:
            self._herald_handle.__exit__(None, None, None)
        if self._herald_handle is not None and (failed := self._core.herald_failures()):
            self._log.warning(f"{failed} CRASHED event(s) could not be published by the core (said above)")
        self._herald_handle = None
        if self._spare_maker is not None:
            self._spare_maker.shutdown(wait=True)
        with self._lock:
            spare, self._spare = self._spare, None
        if spare is not None:  # it winds down while the nodes do
            self._core.request_stop(spare.child)
        self._stop_all([h.detail for h in hosted_nodes])
        self._reclaimer.shutdown(wait=True, cancel_futures=True)  # before the core goes: it reads dead frames
        if spare is not None:
            self._retire_spare(spare)
        self._core.close(kill=True)
        if self.cgroups is not None:
            for problem in self.cgroups.close():
                self._log.error(f"cgroup left behind: {problem}")

    # -- what runs in the child -------------------------------------------------

    def _spin_until_stopped(self, proc: _NodeProcess) -> None:
        """The child's loop: one callback at a time until asked to stop, as
        the executor's spin_once runs them, stamping the board when each
        starts and recording progress when it ends. It starts once the
        container lets it (``run``)."""
        _name_this_process(proc.full_name)
        self.board.set_pid(proc.slot, os.getpid())
        wait_for_go()
        executor = proc.executor
        while not stop_requested():
            try:
                handler, _, _ = executor.wait_for_ready_callbacks(timeout_sec=None)
            except (ShutdownException, ExternalShutdownException, TimeoutException, ConditionReachedException):
                continue
            self.board.busy(proc.slot)
            try:
                handler()
            finally:
                self.board.beat(proc.slot)
            if handler.exception() is not None:
                raise handler.exception()
            handler.result()

    def _fresh_target(self, proc: _NodeProcess, cls: type[Node], args: NodeArguments) -> Callable[[], None]:
        """A per-node child: its own Context, held by a placeholder node."""

        def run() -> None:
            ctx, placeholder = held_context(lambda: self._new_context(args.forward_global_arguments))
            self._build_and_spin(proc, ctx, cls, args, placeholder)

        return run

    def _shared_target(self, proc: _NodeProcess, cls: type[Node], args: NodeArguments) -> Callable[[], None]:
        """A shared-profile child: the node is built on the container's
        Context, but here, in its own process, like a per-node one: a
        constructor that crashes ends this process, not the container."""

        def run() -> None:
            self._build_and_spin(proc, self._context, cls, args, None)

        return run

    def _build_and_spin(
        self, proc: _NodeProcess, ctx: Context, cls: type[Node], args: NodeArguments, placeholder: Placeholder | None
    ) -> None:
        """In a node's child: build the node on ``ctx``, say READY (or
        FAILED), spin it until asked to stop, then tear it all down. A
        per-node child's ``placeholder`` (placeholder.py), which holds its
        own Context's participant, goes once the node holds it too, or last
        after a failed construction: its destruction, off the GIL, then
        deletes the participant. ``placeholder`` None: ``ctx`` is the
        container's (shared profile), which the child leaves as it is."""
        try:
            node = construction.construct(cls, args, ctx, proc.unique_id)
        except Exception as exc:
            # construct() has destroyed whatever node was half made; the
            # participant goes with the placeholder, and its threads end.
            proc.error = str(exc) if isinstance(exc, LoadError) else f"{type(exc).__name__}: {exc}"
            if placeholder is not None:
                release_context(ctx, placeholder)
            proc.handoff.post(FAILED)
            return
        if placeholder is not None:
            placeholder.destroy_node()
        executor = SingleThreadedExecutor(context=ctx)
        executor.add_node(node)
        proc.stop_guard = node.create_guard_condition(_stopping)
        proc.node, proc.executor = node, executor
        proc.full_name = node.get_fully_qualified_name()
        proc.handoff.post(READY)
        if placeholder is None:
            # On the container's Context: once this process has ended
            # cleanly the container destroys the node (_destroy_built), one
            # after another at its shutdown instead of every node process at
            # once on one GIL (96 nodes: 1.5 s against 3 s).
            self._spin_until_stopped(proc)
            return
        try:
            self._spin_until_stopped(proc)
        finally:
            # Also after a callback raised: the participant's threads must
            # end (else this process outlives its node) and its SHM segments
            # be unlinked; then the exception ends us (1).
            executor.shutdown()
            construction.destroy(node)
            release_context(ctx)

    def _new_context(self, forward_global_arguments: bool) -> Context:
        """A node process's own rclpy Context, with the container's global ROS
        arguments if the node is to see them."""
        ctx = Context()
        ros_args = self._container_argv if forward_global_arguments else []
        rclpy.init(args=ros_args, context=ctx, signal_handler_options=SignalHandlerOptions.NO)
        return ctx

    # -- the warm spare (spare.py) ------------------------------------------------

    def _want_spare(self) -> None:
        """Have a spare made, on the spare maker's thread, if there is none."""
        if self._spare_maker is None:
            return
        try:
            self._spare_maker.submit(self._make_spare)
        except RuntimeError:  # shut down: the container is closing
            pass

    def _make_spare(self) -> None:
        """On the spare maker's thread: make a spare if there is none."""
        spare = Spare()
        target = spare_target(spare, lambda: self._new_context(False), self._build_and_spin)
        with self._lock:
            if self._spare is not None or self._closing:
                return
            try:
                spare.child = self._core.spawn(target)
            except Exception as exc:
                self._log.warning(f"could not make a spare process for the next load: {exc}")
                return
            self._name_dump(spare.child, "spare")
            self._spare = spare

    def _take_spare(self, args: NodeArguments) -> Spare | None:
        """The spare, if it can serve this load (caller holds self._lock)."""
        spare = self._spare
        if spare is None or not serves(args):
            return None
        self._spare = None
        return spare

    def _retire_spare(self, spare: Spare) -> None:
        """Wait for a spare asked to stop (it cleans up and ends), as long as
        a node is given; then SIGKILL."""
        death = self._core.wait(spare.child, STOP_TIMEOUT_S)
        if death is None:
            self._core.kill(spare.child, signal.SIGKILL)
            death = self._core.wait(spare.child)
        self._let_spare_go(spare, death)

    def _let_spare_go(self, spare: Spare, death: Death) -> None:
        if death.exit_code == 0 and not death.repaired:
            self._core.release(spare.child)
        else:  # its participant may be half made, or locked: leave it
            self._core.abandon(spare.child)

    # -- parent side --------------------------------------------------------------

    def _await_construction(self, proc: _NodeProcess) -> None:
        word = proc.handoff.wait(CONSTRUCT_TIMEOUT_S)
        if word == READY:
            return
        if word is None:
            self._core.kill(proc.child, signal.SIGKILL)
            why = f"the node was not constructed within {CONSTRUCT_TIMEOUT_S:.0f} s; its process was killed"
        elif word == FAILED:
            why = proc.error
        else:  # DIED, posted by _on_core_event
            why = f"the node's process died during construction ({_describe(proc.death)})"
        clean = word == FAILED
        if self._core.wait(proc.child, FAILED_EXIT_TIMEOUT_S if clean else None) is None:
            self._log.warning(
                f"unique_id {proc.unique_id}: its process did not end within "
                f"{FAILED_EXIT_TIMEOUT_S:g} s of a failed construction: SIGKILL"
            )
            self._core.kill(proc.child, signal.SIGKILL)
            self._core.wait(proc.child)
            clean = False
        with self._lock:
            proc.handoff.close()
            proc.state = "gone"
        self._forget(proc, leak=not clean)
        raise LoadError(why)

    def _stop_all(self, procs: list[_NodeProcess]) -> None:
        """Cancel, SIGTERM, wait up to 500 ms, SIGKILL; reap; release."""
        live = []
        for proc in procs:
            with self._lock:
                if proc.state != "running":
                    continue
                proc.state = "stopping"
            if proc.cgroup is not None:
                self.cgroups.unthrottle(proc.cgroup)  # type: ignore[union-attr]  # with --cgroups only
            self._core.request_stop(proc.child)
            self._core.kill(proc.child, signal.SIGTERM)
            live.append(proc)
        # Woken last, all at once: a woken node process wants the GIL, and
        # with some awake each core call above would wait for it again.
        for proc in live:
            _wake(proc)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for proc in live:
            death = self._core.wait(proc.child, timeout=max(0.0, deadline - time.monotonic()))
            if death is None:
                self._log.warning(
                    f"{proc.full_name} (pid {proc.child.pid}) did not stop "
                    f"within {STOP_TIMEOUT_S * 1000:.0f} ms: SIGKILL"
                )
                self._core.kill(proc.child, signal.SIGKILL)
                death = self._core.wait(proc.child)
            clean = death is not None and death.exit_code == 0
            if clean and proc.profile == SHARED:
                self._destroy_built(proc)
            self._forget(proc, leak=not clean, death=death)

    def _forget(self, proc: _NodeProcess, *, leak: bool, death: Death | None = None) -> None:
        with self._lock:
            self._by_pid.pop(proc.child.pid, None)
            proc.state = "gone"
        self.board.unregister(proc.unique_id)
        proc.slot = -1
        if leak:
            dead = death if proc.node is not None else None  # a built node's death: its memory to give back
            self._core.abandon(proc.child, hold_context=dead is not None)  # its slot out of use until then
            self.leaked.append(proc)
            self._log.warning(
                f"unique_id {proc.unique_id}: the dead process's node, executor"
                + (" and DDS participant" if proc.profile != SHARED else "")
                + " are left in memory (destroying them could block on a lock it held); "
                f"{len(self.leaked)} such leak(s) so far"
            )
            if dead is not None:
                try:
                    self._reclaimer.submit(self._give_back, proc, dead)
                except RuntimeError:  # closing: nothing to let go of, the slot's context back
                    self._core.give_back(proc.child)
        else:
            self._core.release(proc.child)
        if proc.cgroup is not None:  # the process is reaped (above): the group is empty
            cgroup, proc.cgroup = proc.cgroup, None
            self.cgroups.remove(cgroup)  # type: ignore[union-attr]  # with --cgroups only

    def _give_back(self, proc: _NodeProcess, death: Death) -> None:
        """Let go of the plain data that only the dead node's objects reach
        (reclaim.py), then give its slot's memory back and its context to
        the pool (held since its death: no other process took its slot)."""
        began, log = time.monotonic(), self._log.info
        try:
            said = self._let_go(proc, death)
        except Exception as exc:  # a bug of ours: said, not lost in the executor's future
            said, log = f"its memory stays: {type(exc).__name__}: {exc}\n{traceback.format_exc()}", self._log.error
        finally:
            drained = self._core.give_back(proc.child)
        took_ms = (time.monotonic() - began) * 1e3
        log(f"unique_id {proc.unique_id}: {said}{_drained(drained)} ({took_ms:.0f} ms)")

    def _let_go(self, proc: _NodeProcess, death: Death) -> str:
        """What only the dead node reached, let go of (reclaim.py); in words."""
        if death.alloc_faulted:
            return "its memory stays: it died of a fault of its own, and its heap may be torn"
        frames = self._core.dead_frame_refs(proc.child)
        if frames is None:
            return "its memory stays: its Python frames could not be read whole"
        try:
            done = reclaim.release([proc.node, proc.executor], frames, torn=death.gil_repaired)
        except reclaim.Refused as why:
            return f"its memory stays: {why}"
        proc.kept = done.kept
        return (
            f"let go of what only its dead process reached: {done.emptied} list(s), dict(s), set(s) or "
            f"bytearray(s) emptied, {len(done.kept)} object(s) of other types kept (their end could run code), "
            f"{done.alive} of the {done.found} found reachable from elsewhere"
            + (f", {done.suspect} its last instruction may have been changing" if done.suspect else "")
        )

    def _on_core_event(self, event: CoreEvent) -> None:
        if isinstance(event, MutexReport):  # its dead holder may be forgotten already
            mutex_reports.handle(event, self._log)
            return
        with self._lock:
            proc = self._by_pid.get(event.pid)
            spare = self._spare if proc is None and self._spare and self._spare.child.pid == event.pid else None
            if spare is not None and isinstance(event, Death):
                self._spare = None
        if spare is not None:
            if isinstance(event, Death):
                # Exit 0: it was asked to stop by a signal (the container's
                # process group being stopped, say).
                log = self._log.info if event.exit_code == 0 else self._log.warning
                log(
                    f"the spare process for the next load (pid {event.pid}) ended: "
                    f"{_describe(event)}; the next load makes another"
                )
                self._let_spare_go(spare, event)
            return
        if proc is None:
            return
        if isinstance(event, StopRequested):
            # Someone sent the child SIGTERM/SIGINT: let its executor see the flag.
            if event.by_signal:
                proc.stop_signal = event.signal
                _wake(proc)
            return
        assert isinstance(event, Death)
        with self._lock:
            proc.death = event
            state = proc.state
            if state == "starting" and not proc.handoff.closed:
                proc.handoff.post(DIED)
            elif state == "running":
                proc.state = "dead"
        if state == "running":
            self._crashed(proc, event)

    def _name_dump(self, child: Child, name: str) -> None:
        """--core-dumps: the file the child's dump goes to, named after what
        it runs (core_dumps.path_for)."""
        if self._core_dumps is not None:
            self._core.name_dump(child, str(core_dump_path(self._core_dumps, name, child.pid)))

    def abort(self, unique_id: int, why: str) -> bool:
        """End a running node's process with SIGABRT: its crash report (the
        native and Python stacks of what it was doing) goes to the log, and
        its death is reported as any crash is, with ``why`` added. False if
        no running node has that id."""
        with self._lock:
            proc = next((p for p in self._by_pid.values() if p.unique_id == unique_id and p.state == "running"), None)
            # Its event must say why: taken back from the core first.
            if proc is None or proc.aborted or not self._core.disarm_crashed(proc.child):
                return False
            proc.aborted = why
        self._log.error(
            f"{proc.full_name} (unique_id {unique_id}, pid {proc.child.pid}): {why}; "
            "aborting its process (SIGABRT), its stacks follow"
        )
        self._core.kill(proc.child, signal.SIGABRT)
        return True

    def _board_repaired(self, repair: BoardRepair) -> None:
        # Runs in whichever process locked the board next (maybe a child).
        self._log.warning(
            "progress board: its lock's owner died holding it (EOWNERDEAD); repaired "
            f"{len(repair.torn_slots)} half-written slot(s) of unique_id(s) {list(repair.torn_slots)}"
        )
        for unique_id in repair.torn_slots:
            repairs.record(repairs.PROGRESS_BOARD, unique_id, "a half-written progress-board slot")

    def _crashed(self, proc: _NodeProcess, death: Death) -> None:
        """A node's process ended without being unloaded: a crash, or a clean
        exit after an outside SIGTERM/SIGINT (the container's own process
        group being stopped, say)."""
        reason = _describe(death)  # with "after an outside SIGTERM", if so
        if proc.aborted:
            reason += f" by the container: {proc.aborted}"
        # Tell the manager first (it publishes CRASHED, unless the core has);
        # the bookkeeping and its log lines can wait.
        if self._on_death is not None:
            self._on_death(
                proc.unique_id,
                NodeDeath(
                    pid=death.pid,
                    exit_signal=death.exit_signal or 0,
                    exit_code=death.exit_code or 0,
                    reason=reason,
                    allocator_quarantined=death.alloc_quarantined,
                    claimed=death.claimed,
                    stopped=death.exit_code == 0 and proc.stop_signal is not None and not death.repaired,
                    # Read before _forget: until the context is given back no
                    # other node process can take its slot and its count.
                    memory=self._memory_of(proc),
                ),
            )
        if death.core_file:
            self._log.warning(
                f"{proc.full_name} (unique_id {proc.unique_id}, pid {death.pid}): core dump written: "
                f"{death.core_file} ({core_dump_size(death.core_file)})"
            )
        clean = death.exit_code == 0 and not death.repaired
        if clean and proc.profile == SHARED:
            self._destroy_built(proc)
        self._forget(proc, leak=not clean, death=death)


def _drained(counts: tuple[int, int]) -> str:
    """What a dead slot's drain freed (CloneCore.give_back), for the log."""
    said = [f"{n} {kind}" for n, kind in zip(counts, ("Python", "native"), strict=True) if n >= 0]
    return f"; blocks freed into its slot now: {', '.join(said)}" if said else ""


def _say_monitor_priority(refused: str | None, logger: RcutilsLogger) -> None:
    """Whether the monitor thread (deaths, the memory watch) is real-time."""
    if refused is None:
        logger.info(
            "monitor thread: real-time (SCHED_FIFO 1): no node's use of the CPU delays a death's "
            "report or the memory watch"
        )
    else:
        logger.info(
            f"monitor thread: not real-time ({refused}; SCHED_FIFO needs root, CAP_SYS_NICE or an "
            "RLIMIT_RTPRIO of 1): under a full CPU load the memory watch may act later, by more of "
            "its margin"
        )


def _robust_context_lock(context: Context, logger: RcutilsLogger) -> None:
    """In the shared profile every child's executor calls the container's
    ``Context.ok()`` on each spin, and rclpy guards it with a threading.Lock
    (rclpy 7.1: ``Context._lock``, used only as ``with self._lock:``). A
    child SIGKILLed inside it would hold it for good and stop the container's
    executor too (seen: 1 outside SIGKILL in ~180). Swap in a robust mutex:
    what it guards (the context handle, the on-shutdown callbacks) is left
    consistent by every step, so recovery needs no repair."""
    if type(getattr(context, "_lock", None)) is not type(threading.Lock()):
        logger.warning("rclpy Context has no plain _lock here: its lock stays non-robust")
        return
    context._lock = RobustMutex()  # type: ignore[assignment]  # used as a context manager only


_PR_SET_NAME = 15  # <linux/prctl.h>
_TASK_COMM_LEN = 16  # the kernel's bound on a task's name, its NUL included
# Looked up in the container, at import: a node process never dlopens for it
# (the loader's lock is one for every process of the address space).
_prctl = ctypes.CDLL(None).prctl


def _name_this_process(full_node_name: str) -> None:
    """ps, top and /proc/<pid>/comm show a node's process by its node's
    name (its first 15 bytes), as ``ros2 run`` would show the node as a
    process of its own; until then it is "cg-node" (child.c)."""
    name = full_node_name.rsplit("/", 1)[-1].encode()[: _TASK_COMM_LEN - 1]
    _prctl(_PR_SET_NAME, ctypes.c_char_p(name), 0, 0, 0)


def _stopping() -> None:
    """The stop guard's callback: running it is what makes spin_once return
    (a bare Executor.wake() does not: rclpy goes back to waiting)."""


def _wake(proc: _NodeProcess) -> None:
    """Wake the node's executor so its spin loop sees the stop flag."""
    try:
        proc.stop_guard.trigger()
    except Exception:  # not built yet, or the child is tearing it down itself
        pass


def _describe(death: Death | None) -> str:
    """The core's words for a death (cg_describe_death: how it ended, what
    was repaired, its arena, an outside stop signal), and what only Python
    says: whose memory a protection-key fault hit, where it held the GIL, its
    core dump. The core announces no death that has any of these."""
    if death is None:
        return "unknown"
    what = death.text
    if death.pkey_fault is not None:
        fault = death.pkey_fault
        if fault.victim_slot == 0:
            victim = "the container's allocator tables"
        elif fault.victim_pid:
            victim = f"{processes.who(fault.victim_pid)}'s heap"
        elif fault.victim_slot > 0:
            victim = f"allocator slot {fault.victim_slot}'s heap"
        else:
            victim = "memory under a key not its own"
        what += (
            f"; protection-key violation: wrote into {victim} at {fault.addr:#x} "
            f"(key {fault.key}); the write did not land"
        )
    if death.gil_frame:
        what += f"; it held the GIL in {death.gil_frame}"
    if death.core_file:
        what += f"; core dump: {death.core_file}"
    elif death.core_missing:
        what += f"; no core dump: {death.core_missing}"
    return what


_ISOLATED_HOST_IS_A_HOST: type[Host] = IsolatedHost  # mypy holds it to the protocol
