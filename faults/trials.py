"""One trial of each fault: inject it into a rig's container and judge it.

``FAULTS`` (at the end) is the registry: every fault the scenarios inject,
by the name the reports give it. Scenarios run its trials N times and record
the outcomes; ``python -m cloneguard.harness reproduce`` runs one until it does not
survive (the harness finds the registry through the entry point group
``cloneguard.trials``, so the dependency runs one way: faults use the
harness, never the reverse). Every random choice of a trial comes from its
``seed``, so any trial can be replayed.
"""

from __future__ import annotations

import random
import re
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from cloneguard_interfaces.msg import ComponentEvent
from std_msgs.msg import UInt64

from cloneguard.container.memory_budget import MEMORY_LIMIT
from cloneguard.harness import procfs
from cloneguard.harness.client import HarnessTimeout
from cloneguard.harness.rig import DEATHS_PER_CONTAINER, Outcome, Rig, TrialOutcome
from cloneguard.harness.system import longest_gap
from cloneguard.harness.system_trials import timeline, timeline_end

from . import PACKAGE as TESTRIG
from .outside import kill_at

# fault id -> (plugin, parameters, the signal the node dies of)
CALLBACK_FAULTS = {
    "segfault-gil-released": ("faults::SegfaultInCallback", {"mode": "gil-released"}, signal.SIGSEGV),
    "segfault-gil-held": ("faults::SegfaultInCallback", {"mode": "gil-held"}, signal.SIGSEGV),
    "abort": ("faults::AbortInCallback", {}, signal.SIGABRT),
}


def callback_fault(rig: Rig, fault: str, seed: int, index: int) -> Outcome:
    """A node whose timer callback faults 0.1-0.3 s after it starts."""
    plugin, params, sig = CALLBACK_FAULTS[fault]
    resp = rig.client.load_ok(
        TESTRIG, plugin, node_name=f"victim{index}", parameters={**params, "delay": 0.1, "jitter": 0.2, "seed": seed}
    )
    pid = rig.loaded_pid(resp.unique_id)
    return rig.judge_death(resp.unique_id, pid, signal_expected=sig, fault_ns=None)


def raise_in_callback(rig: Rig, seed: int, index: int) -> Outcome:
    """A node whose timer callback raises: its process ends (exit code 1)."""
    resp = rig.client.load_ok(
        TESTRIG, "faults::RaiseInCallback", node_name=f"raiser{index}", parameters={"delay": 0.1, "seed": seed}
    )
    pid = rig.loaded_pid(resp.unique_id)
    out = rig.judge_death(resp.unique_id, pid, signal_expected=0, fault_ns=None)
    if out.survived and out.details.get("exit_code") != 1:
        out.outcome, out.details["why"] = TrialOutcome.FAILED, "exit code was not 1"
    return out


def outside_sigkill(rig: Rig, seed: int, index: int) -> Outcome:
    """A node publishing at 500 Hz, SIGKILLed 0-50 ms after it is loaded."""
    rng = random.Random(seed)
    resp = rig.client.load_ok(
        "cloneguard", "cloneguard::Talker", node_name=f"busy{index}", parameters={"period": 0.002}
    )
    pid = rig.loaded_pid(resp.unique_id)
    sent = kill_at(pid, signal.SIGKILL, rng.uniform(0.0, 0.05))
    return rig.judge_death(resp.unique_id, pid, signal_expected=signal.SIGKILL, fault_ns=sent)


def repaired(rig: Rig, state: str, unique_id: int, *, since_ns: int = 0, wait_s: float = 0.0) -> int:
    """How many REPAIRED events of ``state`` (ComponentEvent.repaired_state)
    for ``unique_id``, of repairs made since ``since_ns`` (host clock), the
    container has published, once at least one has come or ``wait_s`` has
    passed."""

    def match(ev) -> bool:
        stamp = ev.stamp.sec * 1_000_000_000 + ev.stamp.nanosec
        return (
            ev.event_type == ComponentEvent.REPAIRED
            and ev.repaired_state == state
            and ev.unique_id == unique_id
            and stamp >= since_ns
        )

    if wait_s > 0:
        try:
            rig.client.events.wait_for(match, wait_s)
        except HarnessTimeout:
            pass
    return sum(1 for ev in rig.client.events.messages() if match(ev))


def die_holding_lock(rig: Rig, seed: int, index: int) -> Outcome:
    """A node that dies holding the container's progress-board lock, its
    slot half-written; survived means exactly one EOWNERDEAD repair of it."""
    resp = rig.client.load_ok(
        TESTRIG,
        "faults::DieHoldingContainerLock",
        node_name=f"holder{index}",
        parameters={"delay": 0.05, "jitter": 0.1, "seed": seed},
    )
    pid = rig.loaded_pid(resp.unique_id)
    out = rig.judge_death(resp.unique_id, pid, signal_expected=signal.SIGKILL, fault_ns=None)
    if out.survived:
        # The survivor takes this lock after every callback, and has beaten
        # since the death: the repair is done, its event on its way.
        repairs = repaired(rig, "progress-board", resp.unique_id, wait_s=5.0)
        out.details["repairs"] = repairs
        if repairs != 1:
            out.outcome, out.details["why"] = TrialOutcome.FAILED, f"{repairs} EOWNERDEAD repairs logged, expected 1"
    return out


def _kill_when_firing(
    rig: Rig, seed: int, plugin: str, node_name: str, parameters: dict, extra_arguments: dict | None = None, ready=None
) -> Outcome:
    """Load ``plugin``, wait until it announces its fault (it is at work)
    and, with ``ready``, until ``ready()`` returns, SIGKILL it 0-20 ms later
    (from ``seed``) and judge the death."""
    try:
        resp = rig.client.load_ok(
            TESTRIG, plugin, node_name=node_name, parameters=parameters, extra_arguments=extra_arguments or {}
        )
    except HarnessTimeout as exc:
        # The container went on after the last trial's death and stopped later.
        return rig.not_survived(f"a load before the fault got no answer: {exc}")
    pid = rig.loaded_pid(resp.unique_id)
    rig.wait_firing(pid)
    if ready is not None:
        ready()
    sent = kill_at(pid, signal.SIGKILL, random.Random(seed).uniform(0.0, 0.02))
    return rig.judge_death(resp.unique_id, pid, signal_expected=signal.SIGKILL, fault_ns=sent)


# Container arguments of the allocator set-ups the memory faults run under,
# each named, never left to the default (jemalloc where it is installed):
# guarded (the default in isolated mode) and, as baselines, unguarded.
MALLOC_ALLOCATORS = {
    "glibc": ["--allocator", "glibc"],
    "jemalloc": ["--allocator", "jemalloc"],
    "glibc-unguarded": ["--allocator", "glibc", "--no-alloc-guard"],
    "jemalloc-own-unguarded": ["--allocator", "jemalloc", "--no-alloc-guard", "--jemalloc-arenas", "own"],
}


class MallocKill:
    """A drain node that frees what hammers hand it; each trial loads a
    hammer and SIGKILLs it 0-20 ms after it starts allocating."""

    def __init__(self, rig: Rig):
        self.rig = rig
        self._start_drain()

    def _start_drain(self) -> None:
        self.rig.client.load_ok(TESTRIG, "faults::MallocDrain")
        self.freed = self.rig.client.subscribe(UInt64, "/malloc_drain/freed")
        self.freed.wait_count(3, timeout=10)

    def trial(self, seed: int, index: int) -> Outcome:
        rig = self.rig
        out = _kill_when_firing(rig, seed, "faults::MallocHammer", f"hammer{index}", {"delay": 0.0, "seed": seed})
        if out.survived:
            out = rig.keeps_flowing(self.freed, "the drain sibling's freeing", out)
        return out

    def settle(self, out: Outcome) -> None:
        if self.rig.settle(out):
            self._start_drain()


# -- intra-process messaging -----------------------------------------------------

INTRA = {"use_intra_process_comms": True}


class IntraQueueDeath:
    """A listener receiving from a steady talker by reference (both
    intra-process, topic ``/intra_chatter``); each trial loads a third node on
    the same topic that dies by SIGKILL inside a queue operation, holding a
    queue's robust mutex (``op`` "put": a publisher, in the listener's queue;
    "take": a subscription, in its own). Survived: the listener keeps
    receiving, the container goes on, and for "put" the listener's queue was
    repaired (EOWNERDEAD) exactly once."""

    TOPIC = "/intra_chatter"

    def __init__(self, rig: Rig, op: str):
        self.rig, self.op = rig, op
        self._start_pair()

    def _start_pair(self) -> None:
        client = self.rig.client
        self.listener = client.load_ok(
            "cloneguard",
            "cloneguard::Listener",
            node_name="intra_listener",
            parameters={"topic": self.TOPIC},
            extra_arguments=INTRA,
        ).unique_id
        client.load_ok(
            "cloneguard",
            "cloneguard::Talker",
            node_name="intra_talker",
            parameters={"topic": self.TOPIC, "period": 0.005},
            extra_arguments=INTRA,
        )
        self.received = client.subscribe(UInt64, "/intra_listener/received")
        self.received.wait_count(5, timeout=10)

    def trial(self, seed: int, index: int) -> Outcome:
        rig = self.rig
        started = time.time_ns()
        resp = rig.client.load_ok(
            TESTRIG,
            "faults::IntraDieMidQueueOp",
            node_name=f"queue_victim{index}",
            parameters={"op": self.op, "topic": self.TOPIC, "delay": 0.05, "jitter": 0.1, "seed": seed},
            extra_arguments=INTRA,
        )
        pid = rig.loaded_pid(resp.unique_id)
        out = rig.judge_death(resp.unique_id, pid, signal_expected=signal.SIGKILL, fault_ns=None)
        if out.survived:
            out = rig.keeps_flowing(self.received, "the listener's receiving", out, more=5)
        if not out.survived:
            return out
        repairs = repaired(rig, "intra-queue", self.listener, since_ns=started, wait_s=5.0 if self.op == "put" else 0.0)
        out.details["listener_queue_repairs"] = repairs
        if self.op == "put" and repairs != 1:
            out.outcome, out.details["why"] = (
                TrialOutcome.FAILED,
                f"{repairs} repairs of the listener's queue, expected 1",
            )
        return out

    def settle(self, out: Outcome) -> None:
        if self.rig.settle(out):
            self._start_pair()


class PayloadKill:
    """A holder node keeps every message on ``/payload`` for 50 ms, then
    drops it (the last reference); each trial loads a publisher of 256 KiB
    messages that also churns malloc between them, and SIGKILLs it 0-20 ms
    after the holder has taken one of its messages (until then the trial
    would not test what it is about: a publisher killed while a subscriber
    holds its messages; it waits up to 5 s). ``payload`` "malloc": the bytes are the dead
    publisher's malloc'd memory, freed by the holder; "loan": they are a
    block of the container's pool. Survived: the holder releases what it held
    and goes on, and so does the container."""

    def __init__(self, rig: Rig, payload: str):
        self.rig, self.payload = rig, payload
        self._start_holder()

    def _start_holder(self) -> None:
        self.rig.client.load_ok(
            TESTRIG, "faults::PayloadHolder", parameters={"loaned": self.payload == "loan"}, extra_arguments=INTRA
        )
        self.released = self.rig.client.subscribe(UInt64, "/payload_holder/released")
        self.taken = self.rig.client.subscribe(UInt64, "/payload_holder/taken")
        self.released.wait_count(3, timeout=10)
        self.taken.wait_count(3, timeout=10)

    @staticmethod
    def _total(counts) -> int:
        msgs = counts.messages()
        return msgs[-1].data if msgs else 0

    def trial(self, seed: int, index: int) -> Outcome:
        rig = self.rig
        before, taken_before = self._total(self.released), self._total(self.taken)

        def holder_has_one() -> None:
            try:
                self.taken.wait_for(lambda m: m.data > taken_before, 5.0, "the holder taking a message")
            except HarnessTimeout:
                pass  # killed anyway: the trial then says nothing was released

        out = _kill_when_firing(
            rig,
            seed,
            "faults::PayloadPublisher",
            f"payload_pub{index}",
            {"payload": self.payload, "seed": seed},
            INTRA,
            ready=holder_has_one,
        )
        if out.survived:
            out = rig.keeps_flowing(self.released, "the holder's releasing", out)
        if not out.survived:
            return out
        # The holder keeps each message 50 ms: its first release of the dead
        # publisher's messages comes that long after the death, at least.
        try:
            self.released.wait_for(lambda m: m.data > before, 5.0, "release of the dead publisher's messages")
        except HarnessTimeout:
            pass
        out.details["released"] = self._total(self.released) - before
        out.details["taken"] = self._total(self.taken) - taken_before
        if out.details["taken"] == 0:
            out.outcome, out.details["why"] = TrialOutcome.FAILED, "the holder took no message of the publisher's"
        elif out.details["released"] == 0:
            out.outcome, out.details["why"] = (
                TrialOutcome.FAILED,
                "the holder released no message of the publisher's in 5 s",
            )
        return out

    def settle(self, out: Outcome) -> None:
        if self.rig.settle(out):
            self._start_holder()


@dataclass(frozen=True)
class LockFamily:
    """Locks of one kind that nodes of an isolated container share, as the
    lock-death trials use them: the components that die holding one and
    wait for one, the REPAIRED event's ``repaired_state``, and what its
    message names each lock by."""

    holder: str
    waiter: str
    topic: str  # the waiter's, with /progress and /repaired beside it
    repaired_state: str
    names: dict[str, str]  # kind -> what the REPAIRED message calls it
    waiter_callback: bool  # the waiter counts its own repairs on /repaired


PYTHON_LOCKS = LockFamily(
    "faults::DieHoldingPythonLock",
    "faults::WaitsForPythonLock",
    "/python_lock_waiter",
    "python-lock",
    {
        k: f"cloneguard.faults.shared_state.{v}"
        for k, v in {"lock": "LOCK", "rlock": "RLOCK", "condition": "CONDITION", "logging": "HANDLER"}.items()
    },
    waiter_callback=True,
)
# faults/nativelock.c's g_locks: one pthread_mutex_t (40 bytes) of each type.
NATIVE_MUTEXES = LockFamily(
    "faults::DieHoldingNativeMutex",
    "faults::WaitsForNativeMutex",
    "/native_mutex_waiter",
    "native-mutex",
    {"normal": "NORMAL mutex", "recursive": "RECURSIVE mutex", "rwlock": "rwlock"},
    waiter_callback=False,
)
# Other ways a waiter waits on a dead node's NORMAL mutex (the lock doctor
# sees each differently: mutexes.c, heldscan.c), besides pthread_mutex_lock:
# a timed lock retried every 0.2 s, a trylock polled every 1 ms, and the
# relock after a condvar wait (the holder dies holding the mutex while the
# waiter is inside its 20 ms timed wait).
NATIVE_WAITS = ("timedlock", "clocklock", "trylock", "cond-timedwait")
LOCK_DEATH_SIGNALS = {"segfault": signal.SIGSEGV, "sigkill": signal.SIGKILL}


class LockDeath:
    """A waiter node uses one shared lock of ``family`` (``kind``) every
    10 ms; each trial loads a node that takes the same lock and dies holding
    it (``how``: segfault, SIGKILL). Survived: the death is reported, the
    waiter goes on (the lock was taken over or released), one REPAIRED event
    of the family's ``repaired_state`` names the lock and the dead holder,
    and where the waiter has a repair callback, it ran."""

    def __init__(self, rig: Rig, family: LockFamily, kind: str, how: str, wait: str = "lock"):
        self.rig, self.family, self.kind, self.how, self.wait = rig, family, kind, how, wait
        self._start_waiter()

    def _start_waiter(self) -> None:
        waits = {"wait": self.wait} if self.wait != "lock" else {}
        self.rig.client.load_ok(TESTRIG, self.family.waiter, parameters={"kind": self.kind, **waits})
        self.progress = self.rig.client.subscribe(UInt64, f"{self.family.topic}/progress")
        self.repaired = self.rig.client.subscribe(UInt64, f"{self.family.topic}/repaired")
        self.progress.wait_count(5, timeout=10)

    def trial(self, seed: int, index: int) -> Outcome:
        rig, family = self.rig, self.family
        started = time.time_ns()
        callbacks = len(self.repaired)
        resp = rig.client.load_ok(
            TESTRIG,
            family.holder,
            node_name=f"lock_holder{index}",
            parameters={
                "kind": self.kind,
                "how": self.how,
                "delay": 0.05,
                "jitter": 0.1,
                "seed": seed,
                **({"in_cond_wait": True} if self.wait.startswith("cond-") else {}),
            },
        )
        pid = rig.loaded_pid(resp.unique_id)
        out = rig.judge_death(resp.unique_id, pid, signal_expected=LOCK_DEATH_SIGNALS[self.how], fault_ns=None)
        if out.survived:
            out = rig.keeps_flowing(self.progress, "the waiter's use of the lock", out, more=5)
        if not out.survived:
            return out
        repaired(rig, family.repaired_state, resp.unique_id, since_ns=started, wait_s=5.0)
        events = [
            ev.error_message
            for ev in rig.client.events.messages()
            if ev.event_type == ComponentEvent.REPAIRED
            and ev.repaired_state == family.repaired_state
            and ev.unique_id == resp.unique_id
        ]
        name = family.names[self.kind]
        out.details["repairs"] = events
        if len(events) != 1 or name not in events[0] or f"lock_holder{index}" not in events[0]:
            out.outcome = TrialOutcome.FAILED
            out.details["why"] = f"{len(events)} {family.repaired_state} repairs, expected one naming {name}"
            return out
        if family.waiter_callback:
            try:  # the waiter's own repair callback ran for it
                self.repaired.wait_count(callbacks + 1, timeout=5)
            except HarnessTimeout:
                out.outcome, out.details["why"] = TrialOutcome.FAILED, "the waiter's repair callback did not run"
        return out

    def settle(self, out: Outcome) -> None:
        if self.rig.settle(out):
            self._start_waiter()


class _VictimTrials:
    """What the heap-memory faults share: a HeapVictim (``VICTIM``: its
    parameters) in another node's process, checking its buffer every 10 ms
    on /heap_victim/checks; each trial loads one fault node next to it."""

    VICTIM: dict = {}
    CHECKS_AFTER = 10  # the victim's checks, after the fault, that decide

    def __init__(self, rig: Rig):
        self.rig = rig
        self._start_victim()

    def _start_victim(self) -> None:
        self.victim = self.rig.client.load_ok(TESTRIG, "faults::HeapVictim", parameters=self.VICTIM)
        self.checks = self.rig.client.subscribe(UInt64, "/heap_victim/checks")
        self.checks.wait_count(5, timeout=10)

    def _corruptions(self) -> int:
        return self.checks.messages()[-1].data

    def _load_firing(self, plugin: str, name: str, seed: int, **parameters):
        """Load fault node ``plugin`` as ``name`` (with ``parameters``),
        firing 50-150 ms after it starts; (its LoadNode response, its pid)
        once it fired."""
        resp = self.rig.client.load_ok(
            TESTRIG, plugin, node_name=name, parameters={"delay": 0.05, "jitter": 0.1, "seed": seed, **parameters}
        )
        pid = self.rig.loaded_pid(resp.unique_id)
        self.rig.wait_firing(pid)
        return resp, pid

    def _victim_goes_on(self, out: Outcome) -> Outcome:
        """``out`` if the victim goes on checking and never found its buffer
        changed; else what became of it."""
        out = self.rig.keeps_flowing(self.checks, "the victim", out, more=self.CHECKS_AFTER)
        died = not out.survived and self.rig.crash_reason(self.victim.unique_id)
        if died and out.outcome == TrialOutcome.HUNG:  # the damage killed it, and that was said
            out.outcome, out.details["why"] = TrialOutcome.FAILED, f"the victim died: {died}"
        if out.survived and self._corruptions():
            out.outcome, out.details["why"] = TrialOutcome.CORRUPTED, "the victim's buffer was changed"
        return out

    def _unless_it_went_on(self, out: Outcome, resp, pid: int, who: str, why: str) -> Outcome:
        """After the fault node's death was judged ``out``: if it lives on
        instead (nothing caught the fault: the damage went through to the
        victim), unload it. Either way the victim must go on, intact; a
        victim that goes on after the damage went through is corrupted
        (``why``)."""
        went_on = out.fault_node_lived
        if went_on:
            self.rig.client.unload(resp.unique_id)
            out = Outcome(TrialOutcome.SURVIVED, details={"pid": pid, who: "went on"})
        if out.survived:
            out = self._victim_goes_on(out)
        if out.survived and went_on:
            out.outcome, out.details["why"] = TrialOutcome.CORRUPTED, why
        return out

    # what CRASHED must say of a write the keys caught: whose memory it was
    VIOLATION = "protection-key violation: wrote into /heap_victim"

    def _judge_key_violation(self, resp, pid: int) -> Outcome:
        """Survived if the fault node alone was reported CRASHED by SIGSEGV,
        its text naming a protection-key violation in the target's memory
        (``VIOLATION``)."""
        out = self.rig.judge_death(resp.unique_id, pid, signal_expected=signal.SIGSEGV, fault_ns=None)
        if out.outcome == TrialOutcome.SURVIVED:
            # The CRASHED event says what it was, and whose memory.
            reason = self.rig.crash_reason(resp.unique_id)
            out.details["reason"] = reason
            if self.VIOLATION not in reason:
                out.outcome = TrialOutcome.FAILED
                out.details["why"] = f"CRASHED does not say {self.VIOLATION!r}"
        return out

    def settle(self, out: Outcome) -> None:
        if self.rig.settle(out):
            self._start_victim()


class WildWrite(_VictimTrials):
    """Each trial loads a WildWriter that writes 64 bytes into the victim's
    buffer. Survived: the write faulted in the writer alone (CRASHED,
    SIGSEGV, its text naming a protection-key violation in /heap_victim's
    heap) and the victim's buffer is intact. Corrupted: the victim found its
    buffer changed, and the container did not notice (the writer goes on)."""

    CHECKS_AFTER = 3

    def trial(self, seed: int, index: int) -> Outcome:
        rig = self.rig
        before = self._corruptions()
        resp, pid = self._load_firing("faults::WildWriter", f"wild_writer{index}", seed)
        try:
            self.checks.wait_count(len(self.checks) + self.CHECKS_AFTER, timeout=5)
        except HarnessTimeout as exc:
            return rig.not_survived(f"the victim stopped checking its buffer: {exc}")
        if self._corruptions() > before:
            out = Outcome(TrialOutcome.CORRUPTED, details={"pid": pid, "why": "the victim's buffer was changed"})
            if procfs.alive(pid):
                out.details["writer"] = "went on"
                rig.client.unload(resp.unique_id)
            return out
        out = self._judge_key_violation(resp, pid)
        if out.fault_node_lived:
            out.details["why"] = "the write neither landed nor killed the writer"
        return out

    def settle(self, out: Outcome) -> None:
        # A corrupted trial leaves the container as it was: the victim has
        # filled its buffer again, the writer is unloaded.
        if out.outcome == TrialOutcome.CORRUPTED and self.rig.node_deaths() < DEATHS_PER_CONTAINER:
            return
        super().settle(out)


class DoubleFree(_VictimTrials):
    """The victim gives away 64-byte blocks of its own heap and takes back,
    at each check, what others freed of them; each trial loads a
    DoubleFreer that frees one of those blocks twice. Survived: the freer
    alone is reported CRASHED (SIGABRT: the guard found the block already
    handed back) and the victim goes on, its buffer intact. Corrupted: the
    freer went on, and its owner took the block back twice. Not survived:
    the victim stopped (hung, or died: the damage landed in the owner), or
    the container did."""

    VICTIM = {"donate": 1024}

    def trial(self, seed: int, index: int) -> Outcome:
        rig = self.rig
        resp, pid = self._load_firing("faults::DoubleFreer", f"double_freer{index}", seed)
        out = rig.judge_death(resp.unique_id, pid, signal_expected=signal.SIGABRT, fault_ns=None)
        return self._unless_it_went_on(
            out, resp, pid, "freer", "the freer went on; its owner took the block back twice (its heap is corrupted)"
        )


class TablesWildWrite(_VictimTrials):
    """Each trial loads a WildWriter that writes 64 bytes into the
    container's own state: the allocator guard's tables (every slot's
    arena, hooks and hand-over stacks), at an offset from its seed.
    Survived: the write faulted in the writer alone (CRASHED, SIGSEGV, a
    protection-key violation in the container's allocator tables) and the
    victim and the container go on. Corrupted: the write landed (the writer
    went on); the container is replaced after it, its state no longer
    known."""

    VIOLATION = "protection-key violation: wrote into the container's allocator tables"

    def trial(self, seed: int, index: int) -> Outcome:
        resp, pid = self._load_firing("faults::WildWriter", f"wild_writer{index}", seed, target="allocator-tables")
        out = self._judge_key_violation(resp, pid)
        if out.fault_node_lived:
            why = "the write landed in the container's allocator tables"
            return Outcome(TrialOutcome.CORRUPTED, details={"pid": pid, "writer": "went on", "why": why})
        return self._victim_goes_on(out) if out.survived else out

    def settle(self, out: Outcome) -> None:
        if out.outcome == TrialOutcome.CORRUPTED:
            self.rig.restart()
            self._start_victim()
        else:
            super().settle(out)


class SharedWildWrite(WildWrite):
    """WildWrite into a victim whose buffer is a Python object (a
    bytearray): memory every node writes legitimately, which protection
    keys leave open. Measured, not promised: corrupted with keys or
    without."""

    VICTIM = {"memory": "python"}


class UseAfterFree(_VictimTrials):
    """The victim gives away 64-byte blocks of its own heap and takes back,
    at each check, what others freed of them; each trial loads a
    UseAfterFree node that frees one of those blocks and then writes 64
    bytes into it. Survived: the write faulted in the writer alone (CRASHED,
    SIGSEGV, a protection-key violation in /heap_victim's heap) and the
    victim goes on, its buffer intact. Corrupted: the write landed (the
    writer went on) and the victim went on. Not survived: the victim
    stopped (the damage reached its allocator), or the container did."""

    VICTIM = {"donate": 1024}

    def trial(self, seed: int, index: int) -> Outcome:
        resp, pid = self._load_firing("faults::UseAfterFree", f"use_after_free{index}", seed)
        out = self._judge_key_violation(resp, pid)
        return self._unless_it_went_on(
            out, resp, pid, "writer", "the write landed in a block of the victim's heap after it was freed"
        )


class OwnHeapOverflow(_VictimTrials):
    """Each trial loads a HeapOverflow that overflows a block of its own
    heap by 4 KiB and goes on allocating. Survived: the damage stayed in
    the overflowing node (it died of it, or went on and was unloaded) and
    the victim and the container go on, the victim's buffer intact."""

    def trial(self, seed: int, index: int) -> Outcome:
        rig = self.rig
        resp, pid = self._load_firing("faults::HeapOverflow", f"heap_overflow{index}", seed)
        out = rig.judge_death(resp.unique_id, pid, signal_expected=None, fault_ns=None, timeout=3.0)
        if out.fault_node_lived:
            # It went on; its torn heap may still kill it at any moment (CI
            # saw one die during the judgement's probe load). Unloaded, or
            # else it died of it late: judged again.
            if rig.client.unload(resp.unique_id).success:
                out = Outcome(TrialOutcome.SURVIVED, details={"pid": pid, "overflower": "went on"})
            else:
                out = rig.judge_death(resp.unique_id, pid, signal_expected=None, fault_ns=None)
        if out.survived and "overflower" not in out.details:
            out.details["overflower"] = f"died: {rig.crash_reason(resp.unique_id)}"
        return self._victim_goes_on(out) if out.survived else out


# -- out of memory ------------------------------------------------------------------

MiB = 1 << 20
#: What the container of every out-of-memory trial may use: the limit of the
#: memory cgroup of the harness's own it is born in (a fresh one per
#: container); never a leak against the machine's memory.
OOM_CGROUP_LIMIT = 512 * MiB
#: The leaking node's own budget (cloneguard.memory_limit), where it has one.
OOM_BUDGET = 64 * MiB
#: The watch's margin at OOM_CGROUP_LIMIT (memory_watch.py: 2%, at least
#: 64 MiB): it acts once the container's use is within it of the limit.
OOM_WATCH_MARGIN = 64 * MiB
#: faults::MemoryLeak's kinds, and their parameters here: a leak is fast (the
#: quick runs fill a 512 MiB container in about a second) and for ever
#: (steps 0); "huge" is one allocation of 1.5 times what the container may
#: use (on jemalloc with the allocator guard a node's block can be up to
#: 4 GiB: allocguard.c, make_address_map).
OOM_LEAKS = {
    "python": {"kind": "python", "step": 4 * MiB, "period": 0.005},
    "malloc": {"kind": "native", "step": 8 * MiB, "period": 0.005},
    "huge": {"kind": "huge", "step": 3 * OOM_CGROUP_LIMIT // 2},
    "bytearray": {"kind": "bytes", "step": 8 * MiB, "period": 0.005},
}
#: The OOM containers' /diagnostics period (s): their leaks last about a
#: second, and the report draws each node's memory from these reports.
OOM_DIAGNOSTICS_PERIOD_S = 0.1
#: How long a leak may take to be ended (a Python-object leak fills the
#: container slowest, in a few seconds under load).
OOM_JUDGE_S = 30.0
#: The longest the survivor's heartbeat (50 Hz) may pause in a trial.
OOM_MAX_GAP_S = 1.0
#: What the CRASHED of a node ended for its memory says, by cause.
OUT_OF_MEMORY = {
    "budget": re.compile(
        r"out of memory: (?P<used>[\d.]+) MiB in use, over its limit of (?P<limit>[\d.]+) MiB "
        r"\(it asked for (?P<asked>[\d.]+) (?P<unit>[KM])iB more\)"
    ),
    "watch": re.compile(
        r"out of memory: the container used (?P<used>[\d.]+) MiB of the (?P<limit>[\d.]+) MiB it may use, "
        r"and this node process the most: (?P<node>[\d.]+) MiB"
    ),
}


class OutOfMemory:
    """Each trial loads a faults::MemoryLeak that leaks for ever (its kind,
    one of ``OOM_LEAKS``, drawn from the seed) into a container that runs
    in a memory cgroup of OOM_CGROUP_LIMIT. ``cause`` "budget": the leak has
    a budget of its own (OOM_BUDGET, the LoadNode extra argument
    cloneguard.memory_limit), which it reaches while the container has room;
    "watch": it has none, and grows until the container's memory watch ends
    it near the cgroup's limit.

    Survived: the leak alone was ended (CRASHED, SIGKILL, its text saying
    out of memory for the cause's reason: over its budget, or the container
    near its limit and this node the one using the most), the container
    goes on (answers, loads a node), the survivor's heartbeat never paused
    over OOM_MAX_GAP_S, and the kernel's OOM killer never acted in the
    cgroup. Failed: another reason, another node ended, a longer pause, an
    OOM kill. In thread mode (the baseline) a budget is refused (recorded)
    and the leak loaded without one; nothing but the kernel's OOM killer
    can end it, and it ends the container: crashed.

    Each trial records the container's memory before the load, and after
    it let go of what only the dead leak reached (reclaim.py; measured, not
    judged: a native leak's memory stays). The container is replaced, in a
    fresh cgroup, once it has no room left for another budget's worth above
    the watch's margin: after a native leak, not after a Python one whose
    memory came back (the next trial then runs beside what stayed)."""

    def __init__(self, rig: Rig, cause: str):
        if cause not in OUT_OF_MEMORY:
            raise ValueError(f"cause is one of {sorted(OUT_OF_MEMORY)}, not {cause!r}")
        self.rig, self.cause = rig, cause
        if rig.memory_limit != OOM_CGROUP_LIMIT or rig.diagnostics_period_s != OOM_DIAGNOSTICS_PERIOD_S:
            # A rig made without them (reproduce's): replaced by one whose
            # containers each run in a memory cgroup of that limit.
            rig.memory_limit = OOM_CGROUP_LIMIT
            rig.diagnostics_period_s = OOM_DIAGNOSTICS_PERIOD_S
            rig.restart()

    def _load(self, index: int, kind: str, details: dict):
        """The leak's LoadNode response, or None (details["why"] says why)."""
        client = self.rig.client
        name, params = f"leak{index}", {**OOM_LEAKS[kind], "delay": 0.1}
        budget = {MEMORY_LIMIT: f"{OOM_BUDGET // MiB}M"} if self.cause == "budget" else {}
        resp = client.load(TESTRIG, "faults::MemoryLeak", node_name=name, parameters=params, extra_arguments=budget)
        if resp.success:
            return resp
        if budget and self.rig.profile == "threads" and "needs an isolated container" in resp.error_message:
            details["budget"] = f"refused: {resp.error_message}"
            resp = client.load(TESTRIG, "faults::MemoryLeak", node_name=name, parameters=params)
            if resp.success:
                return resp
        details["why"] = f"the leak's load was refused: {resp.error_message}"
        return None

    def trial(self, seed: int, index: int) -> Outcome:
        """One leak, judged; its timeline (the survivor's heartbeat and
        each node's memory, from the load to now) drawn in the report."""
        start = time.monotonic_ns()
        out = self._trial(seed, index)
        out.details["timeline"] = timeline(self.rig, start, timeline_end(start))
        return out

    def _trial(self, seed: int, index: int) -> Outcome:
        rig = self.rig
        kind = random.Random(seed).choice(sorted(OOM_LEAKS))
        details: dict = {"leak": kind}
        started, started_mono = time.time_ns(), time.monotonic_ns()  # events' clock, the recorders'
        if rig.proc.memory_cgroup is not None:
            details["cgroup_use_before_mib"] = round(rig.proc.memory_cgroup.usage() / MiB, 1)
        resp = self._load(index, kind, details)
        if resp is None:
            return Outcome(TrialOutcome.FAILED, details=details)
        loaded_ns = time.time_ns()
        cgroup = rig.proc.memory_cgroup
        assert cgroup is not None  # __init__ made sure
        if rig.profile == "threads":
            return self._thread_mode(details, cgroup)
        pid = rig.loaded_pid(resp.unique_id)
        out = rig.judge_death(resp.unique_id, pid, signal_expected=signal.SIGKILL, fault_ns=None, timeout=OOM_JUDGE_S)
        out.details = {**details, **out.details}
        ev = next(
            (
                e
                for e in rig.client.events.messages()
                if e.event_type == ComponentEvent.CRASHED and e.unique_id == resp.unique_id
            ),
            None,
        )
        if ev is not None:
            out.latency_ms["load_to_crashed"] = (ev.stamp.sec * 1_000_000_000 + ev.stamp.nanosec - loaded_ns) / 1e6
            out.details["reason"] = ev.error_message
        out.details["oom_kills"] = kills = cgroup.oom_kills()
        others = [
            f"{e.full_node_name} ({e.error_message})"
            for e in rig.client.events.messages()
            if e.event_type == ComponentEvent.CRASHED
            and e.unique_id != resp.unique_id
            and e.stamp.sec * 1_000_000_000 + e.stamp.nanosec >= started
        ]
        if others:
            out.details["also_ended"] = others
        if not out.survived:
            return out
        gap = longest_gap(rig.beats, started_mono)
        out.latency_ms["survivor_longest_gap"] = gap * 1e3
        out.details.update(self._given_back(resp.unique_id, cgroup, details.get("cgroup_use_before_mib")))
        said = OUT_OF_MEMORY[self.cause].search(out.details.get("reason", ""))
        why = ""
        if said is None:
            why = f"CRASHED does not say out of memory for its {self.cause}: {out.details.get('reason', '')!r}"
        elif self.cause == "budget" and float(said["limit"]) != OOM_BUDGET / MiB:
            why = f"ended at a limit of {said['limit']} MiB, not its budget of {OOM_BUDGET // MiB} MiB"
        elif self.cause == "watch" and float(said["limit"]) != OOM_CGROUP_LIMIT / MiB:
            why = f"the watch's limit was {said['limit']} MiB, not the cgroup's {OOM_CGROUP_LIMIT // MiB} MiB"
        elif others:
            why = f"another node was ended too: {others[0]}"
        elif kills:
            why = f"the kernel's OOM killer acted {kills} time(s) in the container's cgroup"
        elif gap > OOM_MAX_GAP_S:
            why = f"the survivor's heartbeat paused {gap:.2f} s"
        if said is not None:  # in MiB
            found = said.groupdict()
            unit = found.pop("unit", "M")
            out.details.update(
                {f"{k}_mib": float(v) / (1024 if k == "asked" and unit == "K" else 1) for k, v in found.items()}
            )
        if why:
            out.outcome, out.details["why"] = TrialOutcome.FAILED, why
        return out

    def _given_back(self, unique_id: int, cgroup, before_mib: float | None) -> dict:
        """The container's memory once it let go of what the dead leak
        alone reached (container/isolated/reclaim.py: its log line says
        when, and what), and how much of it stayed since before the load:
        measured, not judged (a native leak's stays)."""
        try:
            said = self.rig.proc.wait_for_log(rf"unique_id {unique_id}: (let go of|its memory stays)[^\n]*", 15.0)
        except HarnessTimeout:
            return {"given_back": "the container said nothing of it within 15 s"}
        after = round(cgroup.usage() / MiB, 1)
        kept = {} if before_mib is None else {"kept_mib": round(after - before_mib, 1)}
        return {"cgroup_use_after_mib": after, "given_back": said[0], **kept}

    def _thread_mode(self, details: dict, cgroup) -> Outcome:
        """The baseline: nothing ends a leak but the kernel's OOM killer,
        which ends the whole container (crashed); hung if it stays alive."""
        rig = self.rig
        code = rig.proc.wait(OOM_JUDGE_S)
        details["oom_kills"] = cgroup.oom_kills()
        if code is None:
            return rig.not_survived(
                f"the leak was not ended within {OOM_JUDGE_S:g} s", Outcome(TrialOutcome.HUNG, details=details)
            )
        return rig.not_survived(
            f"the container died (exit {code}): the kernel's OOM killer acted {details['oom_kills']} time(s)",
            Outcome(TrialOutcome.CRASHED, details=details),
        )

    def settle(self, out: Outcome) -> None:
        rig = self.rig
        if rig.settle(out):
            return
        cgroup = rig.proc.memory_cgroup
        # A container whose dead leak's memory did not come back (a native
        # leak) has no room for another: a fresh one, in a fresh cgroup.
        room = OOM_CGROUP_LIMIT - OOM_WATCH_MARGIN - (cgroup.usage() if cgroup is not None else 0)
        if room < 2 * OOM_BUDGET:
            rig.restart()


# -- the registry ------------------------------------------------------------------


class Trials(Protocol):
    """A fault set up on a rig: one trial from a seed, and what to do after."""

    rig: Rig

    def trial(self, seed: int, index: int) -> Outcome: ...

    def settle(self, out: Outcome) -> None: ...


class _Each:
    """A fault with no set-up of its own: ``fn(rig, seed, index)`` per trial,
    then the rig's own settle (a fresh container after a failure)."""

    def __init__(self, rig: Rig, fn: Callable[[Rig, int, int], Outcome]):
        self.rig, self._fn = rig, fn

    def trial(self, seed: int, index: int) -> Outcome:
        return self._fn(self.rig, seed, index)

    def settle(self, out: Outcome) -> None:
        self.rig.settle(out)


def _callback(name: str) -> Callable[[Rig], Trials]:
    return lambda rig: _Each(rig, lambda r, seed, index: callback_fault(r, name, seed, index))


def _lock_death(family: LockFamily, kind: str, how: str, wait: str = "lock") -> Callable[[Rig], Trials]:
    return lambda rig: LockDeath(rig, family, kind, how, wait)


#: fault name -> make(rig) -> Trials. The malloc faults run under the
#: allocator set-up the rig was started with (MALLOC_ALLOCATORS).
FAULTS: dict[str, Callable[[Rig], Trials]] = {
    **{name: _callback(name) for name in CALLBACK_FAULTS},
    "exception": lambda rig: _Each(rig, raise_in_callback),
    "sigkill-outside": lambda rig: _Each(rig, outside_sigkill),
    "die-holding-robust-mutex": lambda rig: _Each(rig, die_holding_lock),
    "sigkill-during-malloc": MallocKill,
    "intra-die-mid-put": lambda rig: IntraQueueDeath(rig, "put"),
    "intra-die-mid-take": lambda rig: IntraQueueDeath(rig, "take"),
    "sigkill-publisher-holding-messages/malloc": lambda rig: PayloadKill(rig, "malloc"),
    "sigkill-publisher-holding-messages/loan": lambda rig: PayloadKill(rig, "loan"),
    "wild-write-into-another-nodes-heap": WildWrite,
    "wild-write-into-shared-memory": SharedWildWrite,
    "wild-write-into-container-state": TablesWildWrite,
    "double-free-of-another-nodes-block": DoubleFree,
    "use-after-free-of-another-nodes-block": UseAfterFree,
    "heap-overflow-in-own-heap": OwnHeapOverflow,
    "out-of-memory/over-its-budget": lambda rig: OutOfMemory(rig, "budget"),
    "out-of-memory/container-full": lambda rig: OutOfMemory(rig, "watch"),
    **{
        f"die-holding-{prefix}-{kind}/{how}": _lock_death(family, kind, how)
        for prefix, family in (("python", PYTHON_LOCKS), ("native", NATIVE_MUTEXES))
        for kind in family.names
        for how in LOCK_DEATH_SIGNALS
    },
    **{
        f"die-holding-native-normal-{wait}/sigkill": _lock_death(NATIVE_MUTEXES, "normal", "sigkill", wait)
        for wait in NATIVE_WAITS
    },
}
