"""The components of ``bench.intra``: a payload source and a payload sink,
and the floor's trigger and waiter.

Registered as ``bench::PayloadSource``, ``bench::PayloadSink``,
``bench::FloorTrigger`` and ``bench::FloorWaiter`` (entry points of the test
rig's distribution, ``cloneguard-testrig``). They talk through the
intra-process API (:mod:`cloneguard.container.intra`): loaded with
``use_intra_process_comms`` they hand messages over by reference, without it
they are the plain rclpy (DDS) path.

Every message is a std_msgs/UInt8MultiArray of ``size`` bytes whose first
bytes are a header, little-endian::

    0..7   CLOCK_MONOTONIC ns (time.monotonic_ns()) just before publish
    8..11  sequence number within its phase
    12     phase: 0 warm-up, 1 latency, 2 burst, 3 end

CLOCK_MONOTONIC is one clock for every process on the host, so the sink's
``time.monotonic_ns()`` on arrival minus the stamp is the delivery latency,
whichever processes the two nodes run in.

The source, once a subscriber is matched and ``settle`` s have passed:
``warmup`` messages, then ``count`` messages one every ``period`` s (the
latency phase: one at a time), then ``burst`` messages back to back (at most
``burst_seconds``: the throughput phase), then one end message. Each message
is built anew (as a real publisher would: a fresh array, or a fresh loan
filled), and stamped only once built, right before publish. ``payload``:
"plain" publishes an ordinary message, "loan" takes ``pub.loan(size)``,
fills it and publishes it with ``pub.publish_loan(loan, msg, "data")``.

Both publish what they saw as one std_msgs/String (JSON) on ``~/stats``
(reliable, transient local) when done: the source after its end message, the
sink when the end message arrives (or ``timeout`` s after it was built, with
``"complete": false``).

The floor (FloorTrigger → FloorWaiter): what any cross-node wake-up costs in
one interpreter, with nothing of the intra-process path in it. The waiter
makes an rclpy guard condition on its own node (so its own executor waits on
it) and leaves it, under its ``channel``, in this module's registry
(:data:`FLOOR_CHANNELS`): in isolated mode every child shares the one
interpreter, so the trigger (another child) finds the very object there. The
trigger, from a timer callback like the source's, stores a stamp
(CLOCK_MONOTONIC) and the phase in the channel and calls ``.trigger()``; the
waiter's guard-condition callback reads CLOCK_MONOTONIC first thing. Same
phases (warm-up, one per ``period``, end), same ``~/stats`` reports.
"""

from __future__ import annotations

import json
import struct
import time

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.timer import Timer
from std_msgs.msg import String, UInt8MultiArray

from cloneguard.container import intra

HEADER = struct.Struct("<QIB")
WARMUP, LATENCY, BURST, END = 0, 1, 2, 3
PHASES = {WARMUP: "warmup", LATENCY: "latency", BURST: "burst", END: "end"}

STATS_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)
HOUSEKEEPING_PERIOD = 0.1  # s: both nodes keep a timer, so UnloadNode finds them awake


def payload_qos(depth: int) -> QoSProfile:
    """What both ends of the payload topic use: reliable, volatile, KEEP_LAST ``depth``."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


class _Sender(Node):
    """What a source and a trigger share: the phases, one timer tick at a
    time. Once ``_matched()`` and ``settle`` s later: ``warmup`` then
    ``count`` calls of ``_emit`` one per ``period`` s, then (after the last
    one had time to arrive) ``_final()``, then the ``~/stats`` report."""

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        decl = self.declare_parameter
        self._count = decl("count", 50).value
        self._period = decl("period", 0.02).value
        self._warmup = decl("warmup", 5).value
        self._settle = decl("settle", 0.5).value
        self._match_timeout = decl("match_timeout", 30.0).value
        if self._period <= 0 or min(self._count, self._warmup) < 0:
            raise ValueError("period must be positive, counts not negative")
        self._stats_pub = self.create_publisher(String, "~/stats", STATS_QOS)
        self._sent = {name: 0 for name in PHASES.values()}
        self._started_ns = time.monotonic_ns()
        self._matched_ns: int | None = None
        self._error = ""
        self._state = "matching"
        self._next_at = 0.0
        self._housekeeping: Timer | None = None

    def _start_timer(self) -> None:
        # One timer drives every phase; it ticks at the latency phase's period
        # and nothing else runs in this node between two messages.
        self._timer = self.create_timer(self._period, self._step)

    # -- what a sender defines --------------------------------------------------------
    def _matched(self) -> bool:
        raise NotImplementedError

    def _unmatched(self) -> str:
        """Why nothing matched within match_timeout."""
        raise NotImplementedError

    def _emit(self, phase: int, seq: int) -> None:
        raise NotImplementedError

    def _final(self) -> None:
        """After the latency phase: the end message (and whatever precedes it)."""
        self._emit(END, 0)

    def _stats(self) -> dict:
        raise NotImplementedError

    # -- the phases -------------------------------------------------------------------
    def _step(self) -> None:
        now = time.monotonic()
        if now < self._next_at:
            return
        try:
            if self._state == "matching":
                if self._matched():
                    self._matched_ns = time.monotonic_ns()
                    self._state = "warmup"
                    self._next_at = now + self._settle
                elif now - self._started_ns / 1e9 > self._match_timeout:
                    self._error = self._unmatched()
                    self._finish()
                return
            if self._state == "warmup":
                if self._sent["warmup"] < self._warmup:
                    self._emit(WARMUP, self._sent["warmup"])
                    self._next_at = now + self._period
                    return
                self._state = "latency"
            if self._state == "latency":
                if self._sent["latency"] < self._count:
                    self._emit(LATENCY, self._sent["latency"])
                    self._next_at = now + self._period
                    return
                self._state = "final"
                self._next_at = now + max(self._period, 0.2)  # let the last one arrive first
                return
            if self._state == "final":
                self._final()
                self._finish()
        except Exception as exc:  # reported, not raised: the benchmark must hear of it
            self._error = f"{type(exc).__name__}: {exc}"
            self._finish()

    def _finish(self) -> None:
        self._state = "done"
        self._timer.cancel()
        self._housekeeping = self.create_timer(HOUSEKEEPING_PERIOD, lambda: None)
        stats = {
            "sent": self._sent,
            "error": self._error,
            "match_s": None if self._matched_ns is None else (self._matched_ns - self._started_ns) / 1e9,
            **self._stats(),
        }
        self._stats_pub.publish(String(data=json.dumps(stats)))


class _Receiver(Node):
    """What a sink and a waiter share: count what arrives by phase, keep the
    latency phase's latencies, and report on ``~/stats`` when the end
    arrives (or ``timeout`` s after being built, incomplete)."""

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        self._timeout_ns = int(self.declare_parameter("timeout", 120.0).value * 1e9)
        self._received = {name: 0 for name in PHASES.values()}
        self._latency_ns: list[int] = []
        self._latency_seq: list[int] = []
        self._done = False
        self._created_ns = time.monotonic_ns()
        self._stats_pub = self.create_publisher(String, "~/stats", STATS_QOS)
        self._housekeeping = self.create_timer(HOUSEKEEPING_PERIOD, self._check_timeout)

    def _arrived(self, now: int, stamp: int, seq: int, phase: int) -> None:
        name = PHASES.get(phase, "unknown")
        self._received[name] = self._received.get(name, 0) + 1
        if phase == LATENCY:
            self._latency_ns.append(now - stamp)
            self._latency_seq.append(seq)
        elif phase == END:
            self._report(complete=True)

    def _stats(self) -> dict:
        raise NotImplementedError

    def _check_timeout(self) -> None:
        if not self._done and time.monotonic_ns() - self._created_ns > self._timeout_ns:
            self._report(complete=False)

    def _report(self, *, complete: bool) -> None:
        if self._done:
            return
        self._done = True
        stats = {
            "complete": complete,
            "received": self._received,
            "latency_us": [v / 1e3 for v in self._latency_ns],
            "latency_seq": self._latency_seq,
            **self._stats(),
        }
        self._stats_pub.publish(String(data=json.dumps(stats)))


class PayloadSource(_Sender):
    def __init__(self, **kwargs):
        super().__init__("payload_source", **kwargs)
        decl = self.declare_parameter
        topic = decl("topic", "bench_payload").value
        self._size = decl("size", 1024).value
        self._payload = decl("payload", "plain").value
        self._burst = decl("burst", 100).value
        self._burst_seconds = decl("burst_seconds", 2.0).value
        depth = decl("depth", 100).value
        if self._payload not in ("plain", "loan"):
            raise ValueError(f"parameter 'payload' must be 'plain' or 'loan', got {self._payload!r}")
        if self._size < HEADER.size:
            raise ValueError(f"parameter 'size' must be at least {HEADER.size}, got {self._size}")
        if depth < 1 or self._burst < 0:
            raise ValueError("depth must be at least 1, burst not negative")
        # What every message carries beyond its header (copied into each new message).
        self._pattern = (bytes(range(256)) * (self._size // 256 + 1))[: self._size]
        self._pub = intra.create_publisher(self, UInt8MultiArray, topic, payload_qos(depth))
        self._build_ns: list[int] = []  # building a message (not in the latency)
        self._publish_ns: list[int] = []  # inside publish()/publish_loan(), latency phase
        self._burst_first_stamp = None
        self._burst_end_ns = None
        self._start_timer()

    def _matched(self) -> bool:
        return self._pub.get_subscription_count() >= 1

    def _unmatched(self) -> str:
        return f"no subscriber matched within {self._match_timeout} s"

    def _emit(self, phase: int, seq: int) -> None:
        self._send(phase, seq)

    def _send(self, phase: int, seq: int) -> tuple[int, int]:
        """Build one message, stamp it, publish it: (stamp, ns spent inside publish)."""
        t0 = time.monotonic_ns()
        if self._payload == "plain":
            msg = UInt8MultiArray()
            msg.data = self._pattern  # the setter copies it into a fresh array.array (one copy)
            stamp = time.monotonic_ns()
            HEADER.pack_into(msg.data, 0, stamp, seq, phase)
            self._pub.publish(msg)
        else:
            loan = self._pub.loan(self._size)
            buf = loan.buffer
            buf[:] = self._pattern
            msg = UInt8MultiArray()
            stamp = time.monotonic_ns()
            HEADER.pack_into(buf, 0, stamp, seq, phase)
            del buf
            self._pub.publish_loan(loan, msg, "data")
        done = time.monotonic_ns()
        if phase == LATENCY:
            self._build_ns.append(stamp - t0)
            self._publish_ns.append(done - stamp)
        self._sent[PHASES[phase]] += 1
        return stamp, done - stamp

    def _final(self) -> None:
        deadline = time.monotonic_ns() + int(self._burst_seconds * 1e9)
        for seq in range(self._burst):
            stamp, _ = self._send(BURST, seq)
            if self._burst_first_stamp is None:
                self._burst_first_stamp = stamp
            if time.monotonic_ns() >= deadline:
                break
        self._burst_end_ns = time.monotonic_ns()
        self._send(END, 0)

    def _stats(self) -> dict:
        return {
            "role": "source",
            "payload": self._payload,
            "size": self._size,
            "intra": self._pub.intra,
            "build_ns": self._build_ns,
            "publish_ns": self._publish_ns,
            "burst_first_stamp_ns": self._burst_first_stamp,
            "burst_publish_ns": (
                None if self._burst_first_stamp is None else self._burst_end_ns - self._burst_first_stamp
            ),
            "sent_intra": self._pub.sent_intra,
            "sent_dds": self._pub.sent_dds,
        }


class PayloadSink(_Receiver):
    def __init__(self, **kwargs):
        super().__init__("payload_sink", **kwargs)
        decl = self.declare_parameter
        topic = decl("topic", "bench_payload").value
        loaned = decl("loaned", False).value
        depth = decl("depth", 100).value
        self._burst_latency_ns: list[int] = []
        self._burst_first_stamp = None
        self._burst_last_ns = None
        self._sizes: set[int] = set()
        self._by_loan = 0
        self._sub = intra.create_subscription(
            self, UInt8MultiArray, topic, self._on_message, payload_qos(depth), loaned_field="data" if loaned else None
        )

    def _on_message(self, msg) -> None:
        now = time.monotonic_ns()
        if isinstance(msg, intra.LoanedMessage):
            buf = msg.payload
            self._by_loan += msg.loaned
        else:
            buf = msg.data
        stamp, seq, phase = HEADER.unpack_from(buf, 0)
        self._sizes.add(len(buf))
        if phase == BURST:
            if self._burst_first_stamp is None:
                self._burst_first_stamp = stamp
            self._burst_last_ns = now
            self._burst_latency_ns.append(now - stamp)
        self._arrived(now, stamp, seq, phase)

    def _stats(self) -> dict:
        sub = self._sub
        return {
            "role": "sink",
            "intra": sub.intra,
            "loaned": sub.loaned_field is not None,
            "sizes": sorted(self._sizes),
            "by_loan": self._by_loan,
            "burst_first_stamp_ns": self._burst_first_stamp,
            "burst_last_ns": self._burst_last_ns,
            "burst_latency_us": [v / 1e3 for v in self._burst_latency_ns],
            "received_intra": sub.received_intra,
            "received_dds": sub.received_dds,
            "queue_dropped": sub.queue.dropped if sub.intra else None,
        }


class FloorChannel:
    """What a FloorWaiter leaves for its FloorTrigger: its guard condition,
    and the last trigger's (stamp, seq, phase), replaced by one store."""

    __slots__ = ("guard", "last")

    def __init__(self, guard):
        self.guard = guard
        self.last = (0, 0, WARMUP)


# channel name -> FloorChannel of the waiter loaded on it. Shared by every
# node of one interpreter (thread mode, or isolated mode's clone children);
# a process-per-node container has no such sharing: the trigger then finds
# nothing and reports so.
FLOOR_CHANNELS: dict[str, FloorChannel] = {}


class FloorTrigger(_Sender):
    def __init__(self, **kwargs):
        super().__init__("floor_trigger", **kwargs)
        self._channel = self.declare_parameter("channel", "bench_floor").value
        self._trigger_ns: list[int] = []  # inside .trigger(), latency phase
        self._target: FloorChannel | None = None
        self._start_timer()

    def _matched(self) -> bool:
        self._target = FLOOR_CHANNELS.get(self._channel)
        return self._target is not None

    def _unmatched(self) -> str:
        return (
            f"no FloorWaiter on channel {self._channel!r} within {self._match_timeout} s "
            "(it must run in this interpreter: thread or isolated mode)"
        )

    def _emit(self, phase: int, seq: int) -> None:
        target = self._target
        assert target is not None, "a trigger before a FloorWaiter matched"  # _step: only once _matched()
        stamp = time.monotonic_ns()
        target.last = (stamp, seq, phase)
        target.guard.trigger()
        if phase == LATENCY:
            self._trigger_ns.append(time.monotonic_ns() - stamp)
        self._sent[PHASES[phase]] += 1

    def _finish(self) -> None:
        self._target = None
        super()._finish()

    def _stats(self) -> dict:
        return {"role": "trigger", "channel": self._channel, "trigger_ns": self._trigger_ns}


class FloorWaiter(_Receiver):
    def __init__(self, **kwargs):
        super().__init__("floor_waiter", **kwargs)
        self._channel = self.declare_parameter("channel", "bench_floor").value
        if self._channel in FLOOR_CHANNELS:
            raise ValueError(f"channel {self._channel!r} already has a FloorWaiter")
        self._guard = self.create_guard_condition(self._on_trigger)
        self._slot = FloorChannel(self._guard)
        FLOOR_CHANNELS[self._channel] = self._slot

    def _on_trigger(self) -> None:
        now = time.monotonic_ns()
        stamp, seq, phase = self._slot.last
        self._arrived(now, stamp, seq, phase)

    def _stats(self) -> dict:
        return {"role": "waiter", "channel": self._channel}

    def destroy_node(self):
        # The trigger stops using the channel once it has sent its end (the
        # benchmark unloads it first); drop it before the guard condition goes.
        if FLOOR_CHANNELS.get(self._channel) is self._slot:
            del FLOOR_CHANNELS[self._channel]
        return super().destroy_node()
