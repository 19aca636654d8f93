"""A container under test with a witness: what scenarios inject faults into.

A rig is a running container, a client, and one *survivor* node (a
heartbeat) whose beats show that the rest of the container goes on. A trial
injects a fault into a *victim* node, then judges the outcome:

``survived``  the victim's death was reported (CRASHED, right signal) and
              afterwards the survivor still beats, the container answers
              ListNodes and can load a new node;
``hung``      the container process lives but one of those stopped: the
              rig captures a diagnosis (gdb stacks, blocked locks, owners);
``crashed``   the container process itself died;
``failed``    something else went wrong (e.g. no CRASHED for a death).

The rig restarts the container after a trial that did not survive, and
after every ``DEATHS_PER_CONTAINER`` node deaths. With ``memory_limit``
each of its containers is born in a memory cgroup of the harness's own
with that limit, a fresh one per container (memory_cgroup.py).
"""

from __future__ import annotations

import signal
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from cloneguard_interfaces.msg import ComponentEvent
from std_msgs.msg import UInt64

from . import diagnose, firing, procfs, symbols
from .client import ContainerClient, HarnessTimeout, Recorder
from .factory import log_tail
from .node_memory import MemorySample, NodeMemory
from .process import ContainerProcess
from .report.model import TrialOutcome

if TYPE_CHECKING:
    from .factory import ContainerFactory

SURVIVOR = ("cloneguard", "cloneguard::Heartbeat")
CRASH_LOG_LINES = 40  # of a container that died in a trial, kept in the report
FATAL_MARK = "Fatal Python error: "  # faulthandler's first line (container/cli.py enables it)
# The first line of the container's own report of a fatal signal, before
# faulthandler's (isolated mode: container/isolated/clonecore/crash.c): its native
# stack and its faulting thread's Python stack.
CONTAINER_CRASH_MARK = "cloneguard: container pid "
NATIVE_STACK_CHARS = 12000
DEATHS_BEFORE = 5  # node deaths kept with a container death, the latest
FATAL_DUMP_CHARS = 16000
# A rig's container is replaced after this many node deaths. Each dead
# per-node node leaves its DDS participant, sockets and all (by design: a
# dead node's objects are never destroyed); Fast DDS gives participant id p
# of domain D the ports 7400 + 250 D + 10 + 2 p (and +11), so past ~120 of
# them a container binds ports of domain D + 1's range, where another test
# may be running (measured: 2,232 UDP ports in one rig container after ~1,000
# outside kills). Deaths in one container are measured on their own
# (bench.leaks' crash cycles, --restart-limit).
DEATHS_PER_CONTAINER = 100
CURRENT_THREAD = "Current thread "  # faulthandler's header of the faulting thread


def fatal_excerpt(dump: str, limit: int) -> str:
    """faulthandler's dump cut to ``limit`` characters, keeping its first
    line and the faulting thread's stack whole: an isolated container's
    dump lists every thread state, dead nodes' too, and the faulting thread
    can come after a hundred of them."""
    if len(dump) <= limit:
        return dump
    first, _, rest = dump.partition("\n")
    at = rest.find(CURRENT_THREAD)
    current = ""
    if at >= 0:
        end = rest.find("\n\n", at)
        current = rest[at:] if end < 0 else rest[at : end + 1]
        rest = rest[:at] + rest[at + len(current) :]
    head = f"{first}\n{current}\n" if current else f"{first}\n"
    room = max(0, limit - len(head) - 80)
    left_out = len(rest) - room
    cut = f"\n[... {left_out} more characters of the dump left out ...]\n" if left_out > 0 else ""
    return head + rest[:room] + cut


# Container arguments per scenario profile (thread mode, or isolated with a
# participant profile: docs/index.md#words); scenarios are parametrized over these.
# Isolated containers get a long watchdog: a hang is the harness's to judge
# and diagnose (which takes seconds of gdb) before the container's own
# watchdog (10 s by default) ends it; it still ends an abandoned one.
PROFILES = {
    "threads": [],
    "per-node": ["--isolated", "--profile", "per-node", "--watchdog", "120"],
    "shared": ["--isolated", "--profile", "shared", "--watchdog", "120"],
}


@dataclass
class Outcome:
    """One trial's outcome (a TrialOutcome), and what the trial measured."""

    outcome: str
    latency_ms: dict[str, float] = field(default_factory=dict)
    details: dict = field(default_factory=dict)
    diagnosis: diagnose.Diagnosis | None = None
    #: judge_death saw the fault node alive after its timeout, the container
    #: going on (FAILED: the fault did not kill it). What the trial saw then,
    #: not what /proc says later: the node may still die of its fault after.
    fault_node_lived: bool = False

    @property
    def survived(self) -> bool:
        return self.outcome == TrialOutcome.SURVIVED


class Rig:
    def __init__(
        self,
        factory: ContainerFactory,
        profile: str,
        *,
        extra_args: Sequence[str] = (),
        extra_env: dict[str, str] | None = None,
        fastdds_profile: Path | None = None,
        memory_limit: int | None = None,
        diagnostics_period_s: float | None = None,
    ):
        self._factory = factory
        self.profile = profile
        self._args = [*PROFILES[profile], *extra_args]
        #: seconds between the container's /diagnostics (its nodes' memory);
        #: None: its own default. Set it and restart() as memory_limit.
        self.diagnostics_period_s = diagnostics_period_s
        self._env = extra_env
        self._fastdds = fastdds_profile
        #: bytes: each container (each restart's too) runs in a memory
        #: cgroup of its own with this limit (MemoryCgroupUnavailable where
        #: none can be made); set it and restart() to move a rig into one
        self.memory_limit = memory_limit
        self.restarts = 0
        self._start()

    # -- life cycle ---------------------------------------------------------------

    def _start(self) -> None:
        kwargs: dict = {"extra_env": self._env, "memory_limit": self.memory_limit}
        if self._fastdds is not None:
            kwargs["fastdds_profile"] = self._fastdds
        period = self.diagnostics_period_s
        args = self._args + (["--ros-args", "-p", f"diagnostic_updater.period:={period}"] if period else [])
        self.proc: ContainerProcess = self._factory.start(args, **kwargs)
        self.client: ContainerClient = self._factory.connect(self.proc)
        self._memory = NodeMemory(self.client, self.proc.fqn)
        resp = self.client.load_ok(*SURVIVOR, node_name="survivor", parameters={"period": 0.02})
        self.survivor_id = resp.unique_id
        self.beats = self.client.subscribe(UInt64, "/survivor/heartbeat")
        self.beats.wait_count(3, timeout=10)

    @property
    def watched(self) -> dict[str, Recorder]:
        """The topics a trial's timeline draws: the survivor's heartbeat."""
        return {"/survivor/heartbeat": self.beats}

    def memory_by_node(self, since_ns: int = 0, until_ns: int | None = None) -> dict[str, list[MemorySample]]:
        """Each node's memory as the container now running reports it."""
        return self._memory.by_node(since_ns, until_ns)

    def restart(self) -> None:
        self.client.close()
        self.proc.stop()
        self.restarts += 1
        self._start()

    # -- what the harness knows about pids ---------------------------------------------

    def firing_ns(self, pid: int) -> int | None:
        """When the fault in ``pid`` announced itself (time.time_ns()), from the log."""
        return next((ns for _, ns, who in firing.parse(self.proc.log_text()) if who == pid), None)

    def wait_firing(self, pid: int, timeout: float = 10.0) -> int:
        """Wait until the fault in ``pid`` has announced itself; its time_ns."""
        deadline = time.monotonic() + timeout
        while (ns := self.firing_ns(pid)) is None:
            if time.monotonic() >= deadline:
                raise HarnessTimeout(f"the fault in pid {pid} did not fire within {timeout:.0f} s")
            time.sleep(0.02)
        return ns

    def loaded_pid(self, unique_id: int, timeout: float = 10.0) -> int:
        return self.client.wait_for_event(ComponentEvent.LOADED, unique_id=unique_id, timeout=timeout).pid

    # -- judging a trial --------------------------------------------------------------

    def goes_on(self, timeout: float = 5.0) -> str | None:
        """None if the container goes on; else what stopped."""
        if not self.proc.alive():
            return "container exited"
        try:
            seen = len(self.beats)
            self.beats.wait_count(seen + 3, timeout=timeout)
        except HarnessTimeout as exc:
            return f"survivor stopped beating: {exc}"
        try:
            self.client.list(timeout=timeout)
            probe = self.client.load(*SURVIVOR, node_name="probe", timeout=timeout)
            if not probe.success:
                return f"a new load failed: {probe.error_message}"
            self.client.unload(probe.unique_id, timeout=timeout)
        except HarnessTimeout as exc:
            return f"container stopped answering: {exc}"
        return None

    def crash_reason(self, unique_id: int) -> str:
        """The text of load ``unique_id``'s CRASHED event ("" if none yet)."""
        return next(
            (
                e.error_message
                for e in self.client.events.messages()
                if e.event_type == ComponentEvent.CRASHED and e.unique_id == unique_id
            ),
            "",
        )

    def judge_death(
        self, unique_id: int, pid: int, *, signal_expected: int | None, fault_ns: int | None, timeout: float = 5.0
    ) -> Outcome:
        """After a fault in node ``unique_id`` (process ``pid``): what happened."""
        try:
            ev = self.client.wait_for_event(ComponentEvent.CRASHED, unique_id=unique_id, timeout=timeout)
        except HarnessTimeout:
            if procfs.alive(pid) and self.goes_on() is None:
                why = f"the fault did not kill pid {pid} within {timeout:g} s"
                return Outcome(TrialOutcome.FAILED, details={"pid": pid, "why": why}, fault_node_lived=True)
            return self.not_survived(f"no CRASHED event for pid {pid} within {timeout:.0f} s")
        out = Outcome(
            TrialOutcome.SURVIVED,
            details={
                "pid": pid,
                "exit_signal": ev.exit_signal,
                "exit_code": ev.exit_code,
                "allocator_quarantined": ev.allocator_quarantined,
            },
        )
        event_ns = ev.stamp.sec * 1_000_000_000 + ev.stamp.nanosec
        fault_ns = fault_ns if fault_ns is not None else self.firing_ns(pid)
        if fault_ns is not None:
            out.latency_ms["death_to_event"] = (event_ns - fault_ns) / 1e6
        if signal_expected is not None and ev.exit_signal != signal_expected:
            out.outcome = TrialOutcome.FAILED
            out.details["why"] = f"reported signal {ev.exit_signal}, expected {signal.Signals(signal_expected).name}"
            return out
        stopped = self.goes_on()
        if stopped:
            return self.not_survived(stopped, out)
        return out

    def keeps_flowing(self, rec: Recorder, what: str, out: Outcome, more: int = 3, timeout: float = 5.0) -> Outcome:
        """After a death judged ``out``: ``out`` if ``rec`` (a sibling's
        progress topic) gets ``more`` messages within ``timeout``, else the
        not-survived outcome saying that ``what`` stopped."""
        seen = len(rec)
        try:
            rec.wait_count(seen + more, timeout=timeout)
        except HarnessTimeout as exc:
            return self.not_survived(f"{what} stopped: {exc}", out)
        return out

    def not_survived(self, why: str, out: Outcome | None = None) -> Outcome:
        out = out or Outcome(TrialOutcome.HUNG)
        out.details["why"] = why
        if not self.proc.alive():
            out.outcome = TrialOutcome.CRASHED
            out.details["exit_code"] = self.proc.wait(0)
            # The container's last words: the log itself goes when the
            # test's temporary directory does. A container that died of a
            # fault ends its log with faulthandler's dump of every thread
            # (its "Fatal Python error:" line first): kept whole (bounded)
            # beside the last lines before it.
            text = self.proc.log_text()
            before, mark, dump = text.partition(FATAL_MARK)
            before, native_mark, native = before.partition(CONTAINER_CRASH_MARK)
            out.details["log_tail"] = log_tail(before, CRASH_LOG_LINES)
            if native_mark:
                out.details["native_stack"] = symbols.symbolize(native_mark + native)[:NATIVE_STACK_CHARS]
            if mark:
                out.details["fatal_error"] = fatal_excerpt(mark + dump, FATAL_DUMP_CHARS)
            # What died before it, as its CRASHED events said (held the
            # GIL, in which function; what was repaired after each).
            out.details["deaths_before"] = [
                {"node": e.full_node_name, "pid": e.pid, "reason": e.error_message}
                for e in self.client.events.messages()
                if e.event_type == ComponentEvent.CRASHED
            ][-DEATHS_BEFORE:]
        else:
            out.outcome = TrialOutcome.HUNG
            out.diagnosis = diagnose.of_container(self.proc, self.client)
        return out

    def settle(self, outcome: Outcome) -> bool:
        """After a trial: a container that did not survive is replaced, and
        one that has seen DEATHS_PER_CONTAINER node deaths. True when it was
        (what a trial had started in the old one is gone)."""
        if outcome.survived and self.node_deaths() < DEATHS_PER_CONTAINER:
            return False
        self.restart()
        return True

    def node_deaths(self) -> int:
        """CRASHED events this rig's container has published."""
        return sum(1 for e in self.client.events.messages() if e.event_type == ComponentEvent.CRASHED)
