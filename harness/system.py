"""Your own nodes under test: a composition of your components loaded into
a real container, faults injected from outside (nothing in your nodes
changes), and checks over what your topics and services did
(docs/testing-your-nodes.md).

Public, and kept stable (a change that breaks a scenario written against
it is named in CHANGELOG.md first): ``NodeSpec``, ``System`` and its
methods below, ``rate``, ``longest_gap``, ``call_latency``, the
``system_factory`` fixture of the pytest plugin, seeded trials of a
System (``system_trials``, ``SystemTrial``: system_trials.py) and fault
schedules (schedule.py). The rest of
``cloneguard.harness`` is the project's own test rig and may change.

Times are ``time.monotonic_ns()`` of the test process: what a Recorder
stamps each message with, and what ``kill``/``freeze`` return.
"""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from cloneguard_interfaces.msg import ComponentEvent

from . import stops
from .client import ContainerClient, Recorder
from .cpu_starve import CpuStarve
from .crash_report import STACKS_WAIT_S, wait_for_report
from .errors import HarnessTimeout
from .factory import ContainerFactory
from .message_faults import MessageEngine, MessageFault, run_message_fault
from .node_memory import MemorySample, NodeMemory
from .process import ContainerProcess, ExitStatus
from .schedule import run_schedule
from .talk import GoalOutcome, Talker

if TYPE_CHECKING:
    from rclpy.client import Client
    from rclpy.qos import QoSProfile

    from .schedule import At, ScheduledFault

#: How long a load, a death's CRASHED event or a restart is waited for.
WAIT_S = 15.0


@dataclass(frozen=True)
class NodeSpec:
    """One node of the composition: what ``ros2 component load`` takes.
    ``name`` and ``namespace`` empty: the component's own."""

    package: str
    plugin: str
    name: str = ""
    namespace: str = ""
    parameters: Mapping[str, object] = field(default_factory=dict)
    remaps: Mapping[str, str] = field(default_factory=dict)
    extra_arguments: Mapping[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class Running:
    """A node of the composition as the container loaded it."""

    spec: NodeSpec
    unique_id: int
    full_name: str
    pid: int  # its own process in isolated mode; the container's in thread mode


@dataclass(frozen=True)
class Fault:
    """A fault ``System`` injected: into which node (its full name and the
    unique_id it had then), what, from when to when."""

    node: str
    what: str
    start_ns: int
    end_ns: int
    unique_id: int = 0
    # A message fault (message_faults.py): filed under its topic, and how
    # many messages it dropped, delayed, duplicated ... ("dropped": 12).
    counts: Mapping[str, int] = field(default_factory=dict)

    @property
    def kind(self) -> str:
        """What kind of fault: the signal's name (with its place for a
        kill_at: ``SIGKILL at python-lock``), ``freeze`` or ``starve``."""
        return self.what if " at " in self.what else self.what.split()[0]

    @property
    def ends_the_node(self) -> bool:
        """A signal whose default action ends the process (not a freeze,
        not a SIGCONT, SIGCHLD, SIGURG or SIGWINCH)."""
        return self.what.startswith("SIG") and self.what not in _HARMLESS_SIGNALS


_HARMLESS_SIGNALS = {"SIGCONT", "SIGCHLD", "SIGURG", "SIGWINCH", "SIGSTOP", "SIGTSTP", "SIGTTIN", "SIGTTOU"}


class System:
    """A container (``container_args``: ``--isolated`` by default) with
    ``nodes`` loaded in order; with ``memory_limit`` (bytes), in a memory
    cgroup of the harness's own with that limit (memory_cgroup.py), each
    time it is started. Made by the ``system_factory`` fixture, which stops
    it after the test."""

    def __init__(
        self,
        factory: ContainerFactory,
        nodes: Sequence[NodeSpec],
        container_args: Sequence[str] = ("--isolated",),
        memory_limit: int | None = None,
    ):
        if not nodes:
            raise ValueError("a System needs at least one node")
        self._factory = factory
        self.specs = tuple(nodes)
        self.container_args = list(container_args)
        self.memory_limit = memory_limit
        self.faults: list[Fault] = []
        # What message faults draw from unless they name a seed: a seeded
        # trial's seed (system_trials sets it), else 0.
        self.seed = 0
        self._messages: MessageEngine | None = None
        self._messages_lock = threading.Lock()  # faults of a schedule start together
        self.watched: dict[str, Recorder] = {}  # every topic() asked for, by name
        self.proc: ContainerProcess
        self.client: ContainerClient  # of the container now running; a restart makes another
        #: when the container now running was started (time.monotonic_ns()):
        #: what a recorder holds from before it came from an earlier one
        self.started_ns = 0
        self.nodes: dict[str, Running] = {}
        self._start()
        # What a caller keeps, the recorders of topic() and the clients of
        # service(), name topics and services, not a container: they are
        # made on the first container's client, which lives as long as the
        # System, so that they go on across restarts.
        self._watch = self.client
        self._memory = NodeMemory(self._watch, self.proc.fqn)

    def _start(self) -> None:
        self.started_ns = time.monotonic_ns()
        self.proc = self._factory.start(self.container_args, memory_limit=self.memory_limit)
        self.client = self._factory.connect(self.proc)
        self._talk = Talker(self.client)
        self._messages = None  # a new container has no message-fault engine yet
        self.nodes = {}
        for spec in self.specs:
            running = self._load(spec)
            self.nodes[running.full_name] = running

    def load(self, spec: NodeSpec) -> Running:
        """Load one more node into the running container, after the rest:
        it joins the composition (a restart loads it again). The node as
        loaded; AssertionError, saying why, if the load fails (the
        composition is then as it was)."""
        running = self._load(spec)
        self.specs = (*self.specs, spec)
        self.nodes[running.full_name] = running
        return running

    def _load(self, spec: NodeSpec) -> Running:
        resp = self.client.load(
            spec.package,
            spec.plugin,
            node_name=spec.name,
            node_namespace=spec.namespace,
            parameters=dict(spec.parameters),
            remap_rules=[f"{a}:={b}" for a, b in spec.remaps.items()],
            extra_arguments=dict(spec.extra_arguments),
            timeout=WAIT_S,
        )
        if not resp.success:
            raise AssertionError(f"{spec.package}/{spec.plugin} did not load: {resp.error_message}")
        ev = self.client.wait_for_event(ComponentEvent.LOADED, unique_id=resp.unique_id, timeout=WAIT_S)
        return Running(spec, resp.unique_id, resp.full_node_name, ev.pid)

    # -- what to watch ------------------------------------------------------------

    def topic(self, msg_type: type, name: str, qos: QoSProfile | int = 10) -> Recorder:
        """Every message on ``name`` from now on, stamped on arrival. The
        topic is *watched*: seeded trials record what it did in each one."""
        rec = self._watch.subscribe(msg_type, name, qos)
        self.watched[name] = rec
        return rec

    def memory(self, full_name: str, since_ns: int = 0) -> list[MemorySample]:
        """Node ``full_name``'s memory as the container reported it on
        /diagnostics (once a second, or every ``diagnostic_updater.period``), from ``since_ns`` on: each a
        ``MemorySample`` (``at_ns``, on a recorder's clock; ``in_use`` and
        ``limit``, its budget, in bytes, 0: none). Isolated mode only (the
        allocator guard counts it); in thread mode, none. KeyError for a
        name that is none of its nodes'."""
        self.node(full_name)  # a typo is an error, not "no samples"
        return self._memory.by_node(since_ns).get(full_name, [])

    def memory_by_node(self, since_ns: int = 0, until_ns: int | None = None) -> dict[str, list[MemorySample]]:
        """Every node's, as ``memory``, from ``since_ns`` to ``until_ns``."""
        return self._memory.by_node(since_ns, until_ns)

    def service(self, srv_type: type, name: str) -> Client:
        """An rclpy client of ``name``, for ``call_latency``."""
        return self._watch.service_client(srv_type, name)

    # -- talking to the nodes (talk.py) ------------------------------------------------

    def call(self, srv_type: type, name: str, request: object, timeout: float = WAIT_S) -> Any:
        """Call service ``name`` (of type ``srv_type``) with ``request``; its
        answer. HarnessTimeout if it is not offered, or does not answer,
        within ``timeout``."""
        return self._talk.call(srv_type, name, request, timeout)

    def send_goal(self, action_type: type, name: str, goal: object, timeout: float = WAIT_S) -> GoalOutcome:
        """Send ``goal`` to action server ``name``: a GoalOutcome (accepted,
        the feedback it sent, its final status and result), waited for
        within ``timeout``."""
        return self._talk.send_goal(action_type, name, goal, timeout)

    def change_state(self, full_name: str, transition: str, timeout: float = WAIT_S) -> bool:
        """Lifecycle node ``full_name``: ask for ``transition`` by label
        (``configure``, ``activate``, ``deactivate``, ``cleanup``,
        ``shutdown``); whether it made it."""
        return self._talk.change_state(full_name, transition, timeout)

    def get_state(self, full_name: str, timeout: float = WAIT_S) -> str:
        """Lifecycle node ``full_name``'s state: ``unconfigured``,
        ``inactive``, ``active`` or ``finalized``."""
        return self._talk.get_state(full_name, timeout)

    def node(self, full_name: str) -> Running:
        try:
            return self.nodes[full_name]
        except KeyError:
            raise KeyError(f"no node {full_name!r} in this system; it has {sorted(self.nodes)}") from None

    def log_text(self) -> str:
        """The log of the container now running (its stdout and stderr: the
        container's and every node's logging), so far."""
        return self.proc.log_text()

    def wait_for_log(self, pattern: str, timeout: float = WAIT_S) -> re.Match:
        """The first match of regular expression ``pattern`` in that log,
        waited for; HarnessTimeout, with the log's end, if none comes within
        ``timeout``."""
        return self.proc.wait_for_log(pattern, timeout)

    def alive(self) -> bool:
        """Is the container process still running?"""
        return self.proc.alive()

    # -- faults from outside --------------------------------------------------------

    def _own_process(self, full_name: str) -> Running:
        running = self.node(full_name)
        if running.pid == self.proc.pid:
            raise ValueError(
                f"{full_name} runs in the container's own process (thread mode): a signal to it is the "
                "container's; start the System with --isolated to hit one node"
            )
        if not os.path.exists(f"/proc/{running.pid}"):
            raise ValueError(f"{full_name} (pid {running.pid}) is not running: an earlier fault ended it")
        return running

    def kill(self, full_name: str, sig: int = signal.SIGKILL) -> int:
        """Send ``sig`` to the node's process; when it was sent."""
        running = self._own_process(full_name)
        at = time.monotonic_ns()
        os.kill(running.pid, sig)
        self.faults.append(Fault(full_name, signal.Signals(sig).name, at, at, running.unique_id))
        return at

    def kill_at(
        self,
        full_name: str,
        place: str,
        *,
        after: int = 1,
        timeout: float = 5.0,
        sig: int = signal.SIGKILL,
        lock: str = "",
    ) -> int:
        """Kill the node's process at a place in its own code (stops.py's
        ``PLACES``: ``allocation``, ``python-allocation``, ``python-lock``),
        at its ``after``-th pass from now: SIGKILL, or ``sig`` taken there by
        the task that got there (SIGSEGV: a crash, with its crash report and
        any core dump); when it was seen stopped there, just before the
        signal. At ``python-lock``, ``lock`` names the one lock to die
        holding (``my_pkg.shared.CACHE_LOCK``, as REPAIRED events name
        locks). HarnessTimeout if it did not get there within ``timeout``
        (it is left running)."""
        running = self._own_process(full_name)
        at = stops.stop_at(running.pid, place, after=after, timeout=timeout, lock=lock)
        if sig == signal.SIGKILL:
            os.kill(running.pid, signal.SIGKILL)
        else:
            stops.signal_there(running.pid, sig)
        where = f"{place} {lock}" if lock else place
        self.faults.append(Fault(full_name, f"{signal.Signals(sig).name} at {where}", at, at, running.unique_id))
        return at

    def freeze(self, full_name: str, seconds: float) -> tuple[int, int]:
        """Stop the node's process for ``seconds`` (SIGSTOP, then SIGCONT);
        when it was stopped and let go."""
        if not 0 < seconds <= 600:
            raise ValueError("freeze for 0-600 s")
        running = self._own_process(full_name)
        start = time.monotonic_ns()
        os.kill(running.pid, signal.SIGSTOP)
        try:
            time.sleep(seconds)
        finally:
            os.kill(running.pid, signal.SIGCONT)
        end = time.monotonic_ns()
        self.faults.append(Fault(full_name, f"freeze {seconds:g} s", start, end, running.unique_id))
        return start, end

    def crash_report(self, pid: int, timeout: float = STACKS_WAIT_S) -> str | None:
        """The crash report the container wrote for the node process
        ``pid`` (a CRASHED event's ``pid``): the signal and address, its
        Python stack and its native stack with function names where the
        libraries' symbols allow; waited for up to ``timeout`` (the stacks
        follow the CRASHED event). None for a death that writes none (a
        SIGKILL, an exit)."""
        return wait_for_report(self.proc.log_text, pid, timeout)

    def starve(self, full_name: str, cpus: float, seconds: float) -> tuple[int, int]:
        """Hold the node's process to ``cpus`` CPUs (0.001 up) for
        ``seconds``, in a cgroup of the harness's own (cpu_starve.py);
        blocks meanwhile; when it began and ended. CpuStarveUnavailable
        (a RuntimeError saying why) where this machine has no cpu
        controller the harness can use."""
        if not 0 < seconds <= 600:
            raise ValueError("starve for 0-600 s")
        running = self._own_process(full_name)
        with CpuStarve(running.pid, cpus):
            start = time.monotonic_ns()
            time.sleep(seconds)
        end = time.monotonic_ns()
        self.faults.append(Fault(full_name, f"starve {cpus:g} CPU {seconds:g} s", start, end, running.unique_id))
        return start, end

    def message_fault(self, fault: MessageFault) -> Fault:
        """Put a message fault (message_faults.py: ``Drop``, ``Delay`` ...)
        in force for its seconds; blocks meanwhile; the Fault recorded, with
        its counts. The first loads the rig's engine into the container."""
        strangers = [n for n in fault.subscribers if n not in self.nodes]
        if strangers:
            raise ValueError(
                f"{fault.kind}: no node {', '.join(strangers)} in this system to hit the messages of; "
                f"it has {sorted(self.nodes)}"
            )
        with self._messages_lock:
            if self._messages is None:
                self._messages = MessageEngine(self.client)
            engine = self._messages
        seed = self.seed if fault.seed is None else fault.seed
        start, end, counts = run_message_fault(engine, fault, seed)
        recorded = Fault(fault.node, fault.describe(), start, end, counts=counts)
        self.faults.append(recorded)
        return recorded

    def inject(self, schedule: At | ScheduledFault | Iterable[At | ScheduledFault]) -> list[Fault]:
        """Run a fault schedule (schedule.py: faults at times from now, in
        order, overlapping where their times do; a single fault runs at
        once); blocks until the last ends; the faults it injected. An
        error of one fault is raised once every other has ended."""
        return run_schedule(self, schedule)

    def wait_crashed(self, full_name: str, timeout: float = WAIT_S) -> ComponentEvent:
        """The container's CRASHED event for the node's current process."""
        running = self.node(full_name)
        return self.client.wait_for_event(ComponentEvent.CRASHED, unique_id=running.unique_id, timeout=timeout)

    def wait_repaired(self, full_name: str, timeout: float = WAIT_S, what: str = "") -> ComponentEvent:
        """The container's REPAIRED event for what the node's current
        process left behind when it died (``what``: its ``repaired_state``,
        e.g. ``python-lock`` or ``native-mutex``; any if empty)."""
        running = self.node(full_name)

        def repaired(ev: ComponentEvent) -> bool:
            return (
                ev.event_type == ComponentEvent.REPAIRED
                and ev.unique_id == running.unique_id
                and (not what or ev.repaired_state == what)
            )

        return self.client.events.wait_for(repaired, timeout, f"REPAIRED {what or '(any)'} after {full_name}'s death")

    def wait_back(self, full_name: str, timeout: float = WAIT_S) -> Running:
        """Under ``--restart-policy on-crash``: wait until the node is loaded
        again after its death; the new process becomes the node's."""
        old = self.node(full_name)

        def again(ev: ComponentEvent) -> bool:
            return (
                ev.event_type == ComponentEvent.LOADED
                and ev.full_node_name == full_name
                and ev.unique_id != old.unique_id
            )

        ev = self.client.events.wait_for(again, timeout, f"LOADED of {full_name} again")
        running = Running(old.spec, ev.unique_id, full_name, ev.pid)
        self.nodes[full_name] = running
        return running

    def stop(self) -> ExitStatus:
        """Stop the container (SIGTERM, as a launch file's shutdown does);
        how it ended. The test's end stops it anyway; this is for a test
        that starts a second System after the first."""
        return self.proc.stop()

    def restart(self) -> None:
        """A fresh container with the whole composition loaded again (after
        a trial that did not survive, say). Recorders from ``topic()`` and
        clients from ``service()`` go on; what the old container sent stays
        in the recorders (``started_ns`` says when the new one started)."""
        self.proc.stop()
        if self.client is not self._watch:  # else a participant a restart would stay
            self._factory.disconnect(self.client)
        self._start()

    @property
    def restarts_crashed_nodes(self) -> bool:
        """Started with ``--restart-policy on-crash``."""
        args = self.container_args
        pairs = zip(args, args[1:], strict=False)
        return "--restart-policy=on-crash" in args or ("--restart-policy", "on-crash") in pairs

    def recover(self, since_ns: int = 0, timeout: float = WAIT_S) -> list[Running]:
        """The whole composition loaded again after the faults injected since
        ``since_ns``: for every node a signal ended, its CRASHED event, then
        its restart (``--restart-policy on-crash``) or a new load of its
        spec. The nodes it brought back; HarnessTimeout if a death is not
        reported or a node does not come back in time."""
        back = []
        for fault in [f for f in self.faults if f.start_ns >= since_ns and f.ends_the_node]:
            running = self.nodes.get(fault.node)
            if running is None or running.unique_id != fault.unique_id:
                continue  # back already (wait_back), or a node of an earlier container
            self.client.wait_for_event(ComponentEvent.CRASHED, unique_id=fault.unique_id, timeout=timeout)
            if self.restarts_crashed_nodes:
                back.append(self.wait_back(fault.node, timeout))
            else:
                again = self._load(running.spec)
                self.nodes[fault.node] = again
                back.append(again)
        return back

    def node_deaths(self) -> int:
        """CRASHED events this container has published."""
        return sum(1 for e in self.client.events.messages() if e.event_type == ComponentEvent.CRASHED)


# -- checks over what arrived -----------------------------------------------------------


def _between(rec: Recorder, since_ns: int, until_ns: int | None) -> tuple[list[int], int]:
    until = time.monotonic_ns() if until_ns is None else until_ns
    if until <= since_ns:
        raise ValueError("the window ends before it starts")
    return [r.at_ns for r in rec.items() if since_ns <= r.at_ns <= until], until


def rate(rec: Recorder, since_ns: int, until_ns: int | None = None) -> float:
    """Messages per second on ``rec`` between the two times (until now)."""
    stamps, until = _between(rec, since_ns, until_ns)
    return len(stamps) / ((until - since_ns) / 1e9)


def longest_gap(rec: Recorder, since_ns: int, until_ns: int | None = None) -> float:
    """The longest time, in seconds, without a message on ``rec`` between
    the two times (until now), the window's edges counted."""
    stamps, until = _between(rec, since_ns, until_ns)
    edges = [since_ns, *stamps, until]
    return max(b - a for a, b in zip(edges, edges[1:], strict=False)) / 1e9


def call_latency(system: System, client: Client, request: object, timeout: float = 5.0) -> float:
    """Seconds from sending ``request`` on ``client`` (``System.service``)
    to its answer; HarnessTimeout (an AssertionError) if the service is not
    offered, or does not answer, within ``timeout``."""
    if not client.wait_for_service(timeout_sec=timeout):  # discovery is not the call's latency
        raise HarnessTimeout(f"{client.srv_name} is not offered within {timeout:.1f} s")
    start = time.monotonic()
    system.client.call(client, request, timeout)
    return time.monotonic() - start
