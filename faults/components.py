"""Fault components: nodes that fail on purpose, loaded like any other.

Each is an installed entry point of the test rig's distribution
(``cloneguard_testrig``: rig/pyproject.toml), never of the product's,
configured by ROS parameters:

``delay``      seconds from construction to the fault (default 0.2)
``jitter``     extra random seconds in [0, jitter), drawn from ``seed``
``seed``       makes the instant (and any other choice) reproducible

Just before a fault fires the component writes one line to stderr (its
format: harness/firing.py), with a single write(2) so it is in the
container's log before the fault can take the process down. The harness
reads it to measure fault-to-event latency against the CRASHED event's
stamp (same host clock).
"""

from __future__ import annotations

import ctypes
import os
import random
import signal
import time

from rclpy.node import Node

from cloneguard.container import locks

# Imported here, in the container, when the class is looked up: a C library
# loaded for the first time inside a clone child is best avoided.
from cloneguard.faults import _nativelock
from cloneguard.faults._hammer import lib as hammer
from cloneguard.faults._nativelock import lib as nativelock
from cloneguard.harness import firing

from . import shared_state


def announce(fault: str) -> None:
    os.write(2, firing.line(fault, time.time_ns(), os.getpid()))


class _FaultNode(Node):
    """A node whose ``fire()`` runs once, ``delay`` (+ jitter) after start."""

    fault = "fault"

    def __init__(self, default_name: str, **kwargs):
        super().__init__(default_name, **kwargs)
        delay = self.declare_parameter("delay", 0.2).value
        jitter = self.declare_parameter("jitter", 0.0).value
        seed = self.declare_parameter("seed", 0).value
        if delay < 0 or jitter < 0:
            raise ValueError("parameters 'delay' and 'jitter' must not be negative")
        self.rng = random.Random(seed)
        when = delay + self.rng.uniform(0.0, jitter)
        self._timer = self.create_timer(max(when, 1e-3), self._once)

    def _once(self):
        self._timer.cancel()
        announce(self.fault)
        self.fire()

    def fire(self):
        raise NotImplementedError


class SegfaultInCallback(_FaultNode):
    """SIGSEGV from a NULL read in a timer callback.

    ``mode`` "gil-held": through ctypes.string_at(0), which runs strlen(NULL)
    without releasing the GIL, so the process dies holding it. "gil-released": through
    libc memcpy called via ctypes.CDLL, which releases the GIL first.
    """

    fault = "segfault"

    def __init__(self, **kwargs):
        super().__init__("segfault", **kwargs)
        self.mode = self.declare_parameter("mode", "gil-held").value
        if self.mode not in ("gil-held", "gil-released"):
            raise ValueError(f"parameter 'mode' must be 'gil-held' or 'gil-released', got {self.mode!r}")
        self.fault = f"segfault-{self.mode}"

    def fire(self):
        if self.mode == "gil-held":
            ctypes.string_at(0)  # strlen(NULL); string_at(0, n) would not read at all
        else:
            libc = ctypes.CDLL(None)
            buf = ctypes.create_string_buffer(1)
            libc.memcpy(buf, ctypes.c_void_p(0), ctypes.c_size_t(1))


class AbortInCallback(_FaultNode):
    """abort() in a timer callback (SIGABRT, with the GIL held)."""

    fault = "abort"

    def __init__(self, **kwargs):
        super().__init__("abort", **kwargs)

    def fire(self):
        os.abort()


class RaiseInCallback(_FaultNode):
    """An exception nobody catches, raised from a timer callback."""

    fault = "exception"

    def __init__(self, **kwargs):
        super().__init__("raiser", **kwargs)

    def fire(self):
        raise RuntimeError("uncaught exception injected by faults::RaiseInCallback")


class HangInCallback(_FaultNode):
    """A callback that never returns.

    ``mode`` "sleep": blocks with the GIL released; "spin": loops in Python
    (the interpreter still hands the GIL to others every few ms); "gil":
    blocks in a C call that keeps the GIL (libc sleep() through ctypes.PyDLL),
    so no other Python thread of the process runs again.
    """

    fault = "hang"

    def __init__(self, **kwargs):
        super().__init__("hanger", **kwargs)
        self.mode = self.declare_parameter("mode", "sleep").value
        if self.mode not in ("sleep", "spin", "gil"):
            raise ValueError(f"parameter 'mode' must be 'sleep', 'spin' or 'gil', got {self.mode!r}")
        self.fault = f"hang-{self.mode}"

    def fire(self):
        while True:
            if self.mode == "sleep":
                time.sleep(3600)
            elif self.mode == "gil":
                ctypes.PyDLL(None).sleep(3600)


class SlowConstructor(Node):
    """Takes ``seconds`` (default 12, longer than the 10 s loading fallback)
    to construct."""

    def __init__(self, **kwargs):
        super().__init__("slow", **kwargs)
        seconds = self.declare_parameter("seconds", 12.0).value
        time.sleep(seconds)


class DieInConstructor(Node):
    """Dies by ``signal`` (default SIGKILL) half-way through construction,
    after its publisher exists: a node killed while being built."""

    def __init__(self, **kwargs):
        super().__init__("dies_early", **kwargs)
        name = self.declare_parameter("signal", "SIGKILL").value
        try:
            sig = signal.Signals[name]
        except KeyError:
            raise ValueError(f"parameter 'signal' must name a signal, got {name!r}") from None
        from std_msgs.msg import String

        self._pub = self.create_publisher(String, "~/never", 10)
        announce(f"die-in-constructor-{sig.name}")
        os.kill(os.getpid(), sig)


class DieHoldingContainerLock(_FaultNode):
    """Takes the lock of the container's progress board (a robust mutex of
    the container's), leaves the slot it guards half-written, and dies by
    SIGKILL while holding both. Needs ``--isolated``.

    The kill is sent through libc (ctypes releases the GIL first), so what is
    measured is the robust mutex, not the interpreter lock.
    """

    fault = "die-holding-container-lock"

    def __init__(self, **kwargs):
        super().__init__("lock_holder", **kwargs)
        from cloneguard.container.isolated import board

        current = board.current()
        if current is None:
            raise RuntimeError("faults::DieHoldingContainerLock needs an isolated container (--isolated)")
        self._board = current

    def fire(self):
        slot = self._board.slot_of_pid(os.getpid())
        if slot is None:
            raise RuntimeError(f"pid {os.getpid()} has no slot on the progress board")
        self._board.begin_torn_write(slot)
        libc = ctypes.CDLL(None, use_errno=True)
        libc.kill(os.getpid(), signal.SIGKILL)


class DieHoldingPythonLock(_FaultNode):
    """Takes one of shared_state's Python locks (``kind``: lock, rlock,
    condition, logging) and dies holding it (``how``: "segfault", holding
    the GIL too; "sigkill", through libc, the GIL released). Its sibling
    :class:`WaitsForPythonLock` waits for the same lock. Needs ``--isolated``."""

    fault = "die-holding-python-lock"

    def __init__(self, **kwargs):
        super().__init__("python_lock_holder", **kwargs)
        self.kind = self.declare_parameter("kind", "lock").value
        self.how = self.declare_parameter("how", "sigkill").value
        # Die half-way through acquire instead: the lock word taken, the
        # holder not recorded yet (what a death in that window leaves).
        self.taking = self.declare_parameter("taking", False).value
        if self.kind not in shared_state.KINDS or self.how not in ("segfault", "sigkill"):
            raise ValueError(f"kind must be one of {shared_state.KINDS}, how 'segfault' or 'sigkill'")

    def fire(self):
        if self.taking:
            shared_state.take_word_only(self.kind)
        else:
            shared_state.take(self.kind)
        if self.how == "segfault":
            ctypes.string_at(0)
        else:
            ctypes.CDLL(None).kill(os.getpid(), signal.SIGKILL)


class WaitsForPythonLock(Node):
    """Uses shared_state's ``kind`` lock every ``period`` s and publishes how
    many times on ``~/progress``: it stops if the lock is never given back.
    Its repair callback (container/locks.py) counts the takeovers it made on
    ``~/repaired``, naming the lock in its log."""

    def __init__(self, **kwargs):
        super().__init__("python_lock_waiter", **kwargs)
        from std_msgs.msg import UInt64

        self.kind = self.declare_parameter("kind", "lock").value
        if self.kind not in shared_state.KINDS:
            raise ValueError(f"kind must be one of {shared_state.KINDS}")
        self._count = 0
        self._repaired = 0
        self._msg = UInt64
        self._pub = self.create_publisher(UInt64, "~/progress", 10)
        self._repaired_pub = self.create_publisher(UInt64, "~/repaired", 10)
        locks.on_dead_holder(shared_state.lock_of(self.kind), self._on_dead_holder)
        self._timer = self.create_timer(self.declare_parameter("period", 0.01).value, self._tick)

    def _on_dead_holder(self, death) -> None:
        self._repaired += 1
        self.get_logger().warning(f"took {death.name} over from {death.node} (pid {death.pid})")
        self._repaired_pub.publish(self._msg(data=self._repaired))

    def _tick(self):
        shared_state.use(self.kind)
        self._count += 1
        self._pub.publish(self._msg(data=self._count))


#: The native locks of faults/nativelock.c, by name: g_locks' mutexes,
#: "file", a stdio stream's lock (glibc's own: no owner recorded), and
#: "rwlock", g_rwlock.
NATIVE_LOCKS = {
    "normal": nativelock.NL_NORMAL,
    "recursive": nativelock.NL_RECURSIVE,
    "errorcheck": nativelock.NL_ERRORCHECK,
    "adaptive": nativelock.NL_ADAPTIVE,
    "robust": nativelock.NL_ROBUST,
    "file": -1,
    "rwlock": -2,
}
_FILE, _RWLOCK = -1, -2
_HOW = {"sigkill": nativelock.NL_SIGKILL, "segfault": nativelock.NL_SEGFAULT}
#: How a waiter waits for a mutex: pthread_mutex_lock; pthread_mutex_timedlock
#: or _clocklock in a loop of 0.2 s tries; the relock after a 20 ms
#: pthread_cond_timedwait or _clockwait. For the rwlock: "lock" writes,
#: "read" reads.
NATIVE_WAITS = {
    "lock": nativelock.NL_LOCK,
    "timedlock": nativelock.NL_TIMEDLOCK,
    "clocklock": nativelock.NL_CLOCKLOCK,
    "cond-timedwait": nativelock.NL_COND_TIMEDWAIT,
    "cond-clockwait": nativelock.NL_COND_CLOCKWAIT,
    "trylock": nativelock.NL_TRYLOCK,
    "read": -1,
}


def _native_lock(node: Node) -> int:
    kind = node.declare_parameter("kind", "normal").value
    if kind not in NATIVE_LOCKS:
        raise ValueError(f"parameter 'kind' must be one of {sorted(NATIVE_LOCKS)}, not {kind!r}")
    return NATIVE_LOCKS[kind]


class DieHoldingNativeMutex(_FaultNode):
    """Takes one of nativelock.c's native locks (``kind``) and dies holding
    it (``how``: "sigkill" or "segfault"; the rwlock write-locked); with
    ``taking`` true, half-way through pthread_mutex_lock instead: the lock
    word taken, no owner written; with ``in_cond_wait`` true, only once a
    :class:`WaitsForNativeMutex` waiting ``cond-timedwait`` or
    ``cond-clockwait`` is inside its condvar wait (its next step is the
    relock); with ``waited`` true, only once a task blocks on the mutex
    (as one that holds it a while). :class:`WaitsForNativeMutex` waits for
    the same lock. Needs ``--isolated``."""

    fault = "die-holding-native-mutex"

    def __init__(self, **kwargs):
        super().__init__("native_mutex_holder", **kwargs)
        self.lock = _native_lock(self)
        how = self.declare_parameter("how", "sigkill").value
        self.taking = self.declare_parameter("taking", False).value
        self.in_cond_wait = self.declare_parameter("in_cond_wait", False).value
        self.waited = self.declare_parameter("waited", False).value
        self.reading = self.declare_parameter("reading", False).value  # the rwlock: read-locked
        plain = self.lock not in (_FILE, _RWLOCK, nativelock.NL_ROBUST)
        if how not in _HOW or ((self.taking or self.in_cond_wait or self.waited) and not plain):
            raise ValueError("how must be 'sigkill' or 'segfault'; taking, in_cond_wait and waited need a plain mutex")
        self.how = _HOW[how]

    def fire(self):
        if self.lock == _FILE:
            nativelock.nativelock_die_holding_file(self.how)
        elif self.lock == _RWLOCK:
            (nativelock.nativelock_rw_read_and_die if self.reading else nativelock.nativelock_rw_hold_and_die)(self.how)
        elif self.in_cond_wait:
            nativelock.nativelock_hold_and_die_in_cond_wait(self.lock, self.how)
        elif self.taking:
            nativelock.nativelock_die_taking(self.lock, self.how)
        elif self.waited:
            nativelock.nativelock_hold_and_die_once_waited(self.lock, self.how)
        else:
            nativelock.nativelock_hold_and_die(self.lock, self.how)


# nativelock.c's functions called with the GIL held (ctypes.PyDLL: the
# library cffi loaded, looked up again), as a C extension that does not
# release it around a blocking call (rclpy's publish, into Fast DDS's locks).
_USE_BY_HOLDING_GIL = ctypes.PyDLL(_nativelock.__file__).nativelock_use_by
_USE_BY_HOLDING_GIL.argtypes = (ctypes.c_int, ctypes.c_int)


class WaitsForNativeMutex(Node):
    """Takes and gives back nativelock.c's ``kind`` lock every ``period`` s
    (the GIL released; with ``hold_gil`` true, a plain mutex with the GIL
    held, so that while it waits no Python thread of the container runs),
    the way ``wait`` says (:data:`NATIVE_WAITS`), and publishes how many
    times on ``~/progress``: it stops if the lock is never given back. A
    robust mutex that comes with EOWNERDEAD is made consistent and counted
    on ``~/repaired``."""

    def __init__(self, **kwargs):
        super().__init__("native_mutex_waiter", **kwargs)
        from std_msgs.msg import UInt64

        self.lock = _native_lock(self)
        wait = self.declare_parameter("wait", "lock").value
        allowed = (
            {"lock"}
            if self.lock == _FILE
            else {"lock", "read"}
            if self.lock == _RWLOCK
            else set(NATIVE_WAITS) - {"read"}
        )
        if wait not in allowed:
            raise ValueError(f"parameter 'wait' for kind {self.lock} must be one of {sorted(allowed)}, not {wait!r}")
        self.way = NATIVE_WAITS[wait]
        self._use_by = nativelock.nativelock_use_by
        if self.declare_parameter("hold_gil", False).value:
            if self.lock in (_FILE, _RWLOCK):
                raise ValueError("hold_gil needs a kind of mutex, not the file lock or the rwlock")
            self._use_by = _USE_BY_HOLDING_GIL
        self._count = self._repaired = 0
        self._msg = UInt64
        self._pub = self.create_publisher(UInt64, "~/progress", 10)
        self._repaired_pub = self.create_publisher(UInt64, "~/repaired", 10)
        self._timer = self.create_timer(self.declare_parameter("period", 0.01).value, self._tick)

    def _tick(self):
        if self.lock == _FILE:
            r = nativelock.nativelock_use_file()
        elif self.lock == _RWLOCK:
            r = nativelock.nativelock_rw_use(self.way != -1)
        else:
            r = self._use_by(self.lock, self.way)
        if r < 0:
            raise OSError(-r, os.strerror(-r))
        if r == 1:
            self._repaired += 1
            self._repaired_pub.publish(self._msg(data=self._repaired))
        self._count += 1
        self._pub.publish(self._msg(data=self._count))


class HoldsNativeMutex(Node):
    """Holds nativelock.c's ``kind`` mutex (or write-locks its rwlock) from
    its construction for ``hold`` s, then gives it back: a live owner. With ``orphan`` true, a
    thread of its process takes it and ends instead: an owner that is gone
    but was never a dead node process's."""

    def __init__(self, **kwargs):
        super().__init__("native_mutex_owner", **kwargs)
        self.lock = _native_lock(self)
        orphan = self.declare_parameter("orphan", False).value
        if self.lock in (_FILE, nativelock.NL_ROBUST) or (orphan and self.lock == _RWLOCK):
            raise ValueError("kind must be a plain mutex, or the rwlock (not orphan)")
        hold = self.declare_parameter("hold", 3.0).value
        if self.lock == _RWLOCK:
            r = nativelock.nativelock_rw_hold()
        else:
            r = (nativelock.nativelock_thread_exits_holding if orphan else nativelock.nativelock_hold)(self.lock)
        if r < 0:
            raise OSError(-r, os.strerror(-r))
        self._timer = None if orphan else self.create_timer(hold, self._give_back)

    def _give_back(self):
        assert self._timer is not None  # the timer that called this: none for an orphan
        self._timer.cancel()
        if self.lock == _RWLOCK:
            nativelock.nativelock_rw_release()
        else:
            nativelock.nativelock_release(self.lock)


class MallocHammer(_FaultNode):
    """Allocates and frees without pause from a callback (in C, GIL
    released), handing one block in eight to ring ``ring`` for a
    :class:`MallocDrain` to free. It never stops: the harness SIGKILLs it at a
    random instant, most likely inside malloc() or free()."""

    fault = "malloc-hammer"

    def __init__(self, **kwargs):
        super().__init__("malloc_hammer", **kwargs)
        self._ring = self.declare_parameter("ring", 0).value
        self._seed = self.rng.getrandbits(64) or 1

    def fire(self):
        hammer.hammer_run(self._ring, self._seed)


class MallocDrain(Node):
    """Frees what a :class:`MallocHammer` hands over on ring ``ring``, every
    ``period`` s, and publishes the running total on ``~/freed``: a sibling
    whose progress shows whether the allocator is still usable."""

    def __init__(self, **kwargs):
        super().__init__("malloc_drain", **kwargs)
        from std_msgs.msg import UInt64

        self._ring = self.declare_parameter("ring", 0).value
        period = self.declare_parameter("period", 0.005).value
        self._freed = 0
        self._msg = UInt64
        self._pub = self.create_publisher(UInt64, "~/freed", 10)
        self._timer = self.create_timer(period, self._drain)

    def _drain(self):
        self._freed += hammer.drain_some(self._ring)
        self._pub.publish(self._msg(data=self._freed))


class MemoryLeak(Node):
    """Keeps memory it never gives back, as a node whose cache or queue grows
    without bound: ``step`` bytes every ``period`` s, of ``kind``

    ``python``   many small Python objects (Python's object allocator)
    ``bytes``    one ``bytearray`` (a big block: glibc mmaps it)
    ``native``   ``malloc`` in C, every page touched
    ``huge``     one allocation of ``step`` bytes, once

    and publishes the bytes it holds on ``~/held`` each time (transient
    local: a late subscriber that asks for it gets the last; a malloc that
    returns NULL leaks nothing: logged, not counted). It leaks from
    ``delay`` s after its construction on, ``steps`` times (0: for ever)."""

    KINDS = ("python", "bytes", "native", "huge")

    def __init__(self, **kwargs):
        super().__init__("memory_leak", **kwargs)
        from rclpy.qos import DurabilityPolicy, QoSProfile
        from std_msgs.msg import UInt64

        TRANSIENT_LOCAL = DurabilityPolicy.TRANSIENT_LOCAL

        self.kind = self.declare_parameter("kind", "bytes").value
        self.step = self.declare_parameter("step", 8 << 20).value
        period = self.declare_parameter("period", 0.02).value
        delay = self.declare_parameter("delay", 0.0).value
        self._steps = self.declare_parameter("steps", 0).value
        if self.kind not in self.KINDS or self.step <= 0 or period <= 0 or delay < 0 or self._steps < 0:
            raise ValueError(f"kind must be one of {self.KINDS}; step, period > 0; delay, steps >= 0")
        self._held: list = []
        self._bytes = 0
        self._msg = UInt64
        # Kept for late subscribers (transient local): in the per-node
        # profile its participant may be discovered after its last step.
        self._pub = self.create_publisher(UInt64, "~/held", QoSProfile(depth=10, durability=TRANSIENT_LOCAL))
        self._libc = ctypes.CDLL(None)
        self._libc.malloc.restype = ctypes.c_void_p
        self._libc.malloc.argtypes = [ctypes.c_size_t]  # not C's int: a step of 4 GiB or more would wrap
        self._start = time.monotonic() + delay
        self._timer = self.create_timer(period, self._leak)

    def _leak(self):
        if time.monotonic() < self._start:
            return
        if self.kind == "python":
            self._held.append([str(i) for i in range(self.step // 64)])  # ~64 B of objects an item
        elif self.kind == "bytes":
            self._held.append(bytearray(self.step))  # zeroed: every page touched
        else:
            block = self._libc.malloc(self.step)
            if not block:  # nothing leaked: say so, count nothing
                self.get_logger().warning(f"malloc({self.step}) returned NULL: this step leaked nothing")
                if self.kind == "huge":
                    self._timer.cancel()
                return
            ctypes.memset(block, 1, self.step)
            self._held.append(block)
        self._bytes += self.step
        self._pub.publish(self._msg(data=self._bytes))
        if self.kind == "huge" or (self._steps and self._bytes >= self._steps * self.step):
            self._timer.cancel()


# -- intra-process messaging (container.intra) ------------------------------


class IntraDieMidQueueOp(_FaultNode):
    """Dies by SIGKILL inside an intra-process queue operation, holding that
    queue's robust mutex: ``op`` "put" is a publisher on ``topic`` killed
    after writing a slot and before publishing it; "take" is a subscription
    on ``topic`` killed after reading its messages and before committing.
    Until ``delay`` it is a plain (intra-process) publisher at ``period`` or
    subscription. Load it with ``use_intra_process_comms``."""

    def __init__(self, **kwargs):
        super().__init__("queue_victim", **kwargs)
        from std_msgs.msg import String

        from cloneguard.container import intra

        self.op = self.declare_parameter("op", "put").value
        if self.op not in ("put", "take"):
            raise ValueError(f"parameter 'op' must be 'put' or 'take', got {self.op!r}")
        self.fault = f"intra-die-mid-{self.op}"
        topic = self.declare_parameter("topic", "chatter").value
        period = self.declare_parameter("period", 0.005).value
        self._String = String
        if self.op == "put":
            self._pub = intra.create_publisher(self, String, topic, 10)
            self._tick = self.create_timer(period, self._publish)
        else:
            self._sub = intra.create_subscription(self, String, topic, lambda msg: None, 10)

    def _publish(self):
        self._pub.publish(self._String(data="from the victim"))

    def fire(self):
        from cloneguard.container import seams

        me = os.getpid()

        def die(q):
            if os.getpid() == me:  # the hook is global: only this node's process
                ctypes.CDLL(None).kill(me, signal.SIGKILL)

        seams.arm(f"queue_mid_{self.op}", die)


class PayloadPublisher(Node):
    """Publishes a ``size``-byte std_msgs/UInt8MultiArray on ``topic`` every
    ``period`` s, and between messages runs bursts of malloc/free (so its
    malloc arena lock is held most of the time, wherever a kill lands).
    ``payload`` "malloc": the message's data is an ordinary array (this
    process's malloc); "loan": a buffer loaned from the container's pool.
    Load it with ``use_intra_process_comms``; the harness SIGKILLs it."""

    def __init__(self, **kwargs):
        super().__init__("payload_pub", **kwargs)
        import array

        from std_msgs.msg import UInt8MultiArray

        from cloneguard.container import intra

        self._payload = self.declare_parameter("payload", "malloc").value
        if self._payload not in ("malloc", "loan"):
            raise ValueError(f"parameter 'payload' must be 'malloc' or 'loan', got {self._payload!r}")
        self._size = self.declare_parameter("size", 256 * 1024).value
        period = self.declare_parameter("period", 0.002).value
        self._burst = self.declare_parameter("burst", 20000).value
        self._seed = self.declare_parameter("seed", 0).value or 1
        topic = self.declare_parameter("topic", "payload").value
        self._array, self._Msg = array.array, UInt8MultiArray
        self._pattern = bytes(range(256)) * (self._size // 256) + bytes(self._size % 256)
        self._pub = intra.create_publisher(self, UInt8MultiArray, topic, 10)
        self._sent = 0
        self._timer = self.create_timer(period, self._tick)

    def _tick(self):
        if self._payload == "malloc":
            data = self._array("B")
            data.frombytes(self._pattern)  # malloc'd here, in this process
            self._pub.publish(self._Msg(data=data))
        else:
            loan = self._pub.loan(self._size)
            loan.buffer[:] = self._pattern
            self._pub.publish_loan(loan, self._Msg(), "data")
        self._sent += 1
        if self._sent == 1:
            announce(f"payload-{self._payload}")
        hammer.hammer_burst(self._seed + self._sent, self._burst)


class PayloadHolder(Node):
    """Holds every message from ``topic`` for ``hold`` s, then releases it
    (the last reference: freeing it is up to this process). Publishes the
    running counts of released messages on ``~/released`` (it stalls if a
    release blocks: on a dead publisher's malloc arena lock, say) and of
    messages taken on ``~/taken``, every 10 ms."""

    def __init__(self, **kwargs):
        super().__init__("payload_holder", **kwargs)
        import collections
        import time

        from std_msgs.msg import UInt8MultiArray, UInt64

        from cloneguard.container import intra

        self._hold_ns = int(self.declare_parameter("hold", 0.05).value * 1e9)
        loaned = self.declare_parameter("loaned", False).value
        topic = self.declare_parameter("topic", "payload").value
        self._now = time.monotonic_ns
        self._held: collections.deque = collections.deque()
        self._released = self._taken = 0
        self._UInt64 = UInt64
        self._sub = intra.create_subscription(
            self, UInt8MultiArray, topic, self._on_message, 50, loaned_field="data" if loaned else None
        )
        self._pub = self.create_publisher(UInt64, "~/released", 10)
        self._taken_pub = self.create_publisher(UInt64, "~/taken", 10)
        self._timer = self.create_timer(0.01, self._release_old)

    def _on_message(self, msg):
        self._held.append((self._now(), msg))
        self._taken += 1

    def _release_old(self):
        cutoff = self._now() - self._hold_ns
        while self._held and self._held[0][0] <= cutoff:
            self._held.popleft()  # the last reference: the payload is freed here
            self._released += 1
        self._pub.publish(self._UInt64(data=self._released))
        self._taken_pub.publish(self._UInt64(data=self._taken))


_libc = ctypes.CDLL(None, use_errno=True)
_libc.malloc.restype = ctypes.c_void_p
_libc.malloc.argtypes = [ctypes.c_size_t]
_libc.free.restype = None
_libc.free.argtypes = [ctypes.c_void_p]


class _NativeCycle:
    """A reference cycle holding a 64-byte block of native heap, malloc'd by
    the process that made it (under its key with --pkeys) and freed by the
    finalizer: on whichever thread the garbage collector runs."""

    freed = 0  # by every instance, in every process (one interpreter)

    def __init__(self, peer=None):
        self.block = _libc.malloc(64)
        ctypes.memset(self.block, 0xC5, 64)
        self.me = self
        self.peer = peer  # a cycle another node made: collected together

    def __del__(self):
        _libc.free(self.block)
        _NativeCycle.freed += 1


class CycleMaker(Node):
    """Makes ``count`` garbage cycles every ``period`` s, each holding a block
    of its own native heap, linked to cycles other CycleMakers left in
    shared_state.CYCLES (so a collection frees several nodes' blocks
    together); every ``collect_every`` ticks it calls ``gc.collect()``
    itself. Publishes the running count of cycles finalized, by anyone, on
    ``~/freed``."""

    def __init__(self, **kwargs):
        super().__init__("cycle_maker", **kwargs)
        from std_msgs.msg import UInt64

        self._count = self.declare_parameter("count", 50).value
        self._collect_every = self.declare_parameter("collect_every", 20).value
        self._ticks = 0
        self._msg = UInt64
        self._pub = self.create_publisher(UInt64, "~/freed", 10)
        self._timer = self.create_timer(self.declare_parameter("period", 0.01).value, self._tick)

    def _tick(self):
        import gc

        for _ in range(self._count):
            peer = shared_state.CYCLES.pop() if shared_state.CYCLES else None
            if peer is not None:
                peer.peer = None  # pairs, not chains back to the first
            shared_state.CYCLES.append(_NativeCycle(peer))
        del shared_state.CYCLES[: -self._count]  # the rest is garbage now
        self._ticks += 1
        if self._ticks % self._collect_every == 0:
            gc.collect()
        self._pub.publish(self._msg(data=_NativeCycle.freed))


class HeapVictim(Node):
    """Keeps a ``size``-byte buffer, filled with a pattern, made at its first
    tick (so in its own process in either profile): with ``memory``
    "native" in its process's native heap (malloc), with "python" a
    bytearray (a Python object: memory every node writes legitimately).
    Every ``period`` s it checks the buffer (a changed one is filled again)
    and publishes on ``~/checks`` how many checks so far found it changed:
    one topic, so that what a check found is in order with the checks
    before it. Where the buffer is: shared_state.HEAP_BUFFERS, by node
    name. With ``donate`` > 0 it also mallocs that many 64-byte blocks for
    other nodes to free (shared_state.DONATED_BLOCKS), and each tick mallocs
    and frees a few of its own, so that it takes back what others freed of
    its blocks."""

    PATTERN = 0xC3

    def __init__(self, **kwargs):
        super().__init__("heap_victim", **kwargs)
        from std_msgs.msg import UInt64

        self._msg = UInt64
        self._size = self.declare_parameter("size", 4096).value
        if not 64 <= self._size <= 1 << 20:
            raise ValueError("parameter 'size' must be 64 B to 1 MiB")
        self._expected = bytes([self.PATTERN]) * self._size
        self._buf = 0
        self._corrupted = 0
        self._pub = self.create_publisher(UInt64, "~/checks", 10)
        self._donate = self.declare_parameter("donate", 0).value
        self._memory = self.declare_parameter("memory", "native").value
        if self._memory not in ("native", "python"):
            raise ValueError(f"parameter 'memory' must be 'native' or 'python', got {self._memory!r}")
        self._timer = self.create_timer(self.declare_parameter("period", 0.01).value, self._tick)

    def _make_buffer(self) -> int:
        if self._memory == "python":
            self._pybuf = bytearray(self._expected)
            return ctypes.addressof((ctypes.c_char * self._size).from_buffer(self._pybuf))
        buf = _libc.malloc(self._size)
        if not buf:
            raise MemoryError("HeapVictim: malloc failed")
        ctypes.memset(buf, self.PATTERN, self._size)
        return buf

    def _tick(self):
        if not self._buf:
            self._buf = self._make_buffer()
            shared_state.HEAP_BUFFERS[self.get_name()] = (self._buf, self._size)
            shared_state.DONATED_BLOCKS[self.get_name()] = [_libc.malloc(64) for _ in range(self._donate)]
        if self._donate:
            for _ in range(8):  # the owner's own malloc takes back what others freed
                _libc.free(_libc.malloc(64))
        if ctypes.string_at(self._buf, self._size) != self._expected:
            self._corrupted += 1
            ctypes.memset(self._buf, self.PATTERN, self._size)
        self._pub.publish(self._msg(data=self._corrupted))


class WildWriter(_FaultNode):
    """A stray write: ``bytes`` bytes (at an offset chosen from ``seed``)
    into the buffer of the HeapVictim named ``victim``, a node of another
    process, or with ``target`` "allocator-tables" into the container's
    allocator guard's tables. Nothing in this node's own code notices;
    whether the write lands or faults is the container's doing."""

    fault = "wild-write"

    def __init__(self, **kwargs):
        super().__init__("wild_writer", **kwargs)
        self.victim = self.declare_parameter("victim", "heap_victim").value
        self.count = self.declare_parameter("bytes", 64).value
        self.target = self.declare_parameter("target", "victim").value
        if self.target == "allocator-tables":
            size = ctypes.c_size_t()
            try:
                cga_tables = _libc.cga_tables  # the guard, preloaded in isolated mode
            except AttributeError:
                raise ValueError("target 'allocator-tables' needs the allocator guard (isolated mode)") from None
            cga_tables.restype = ctypes.c_void_p
            self.span = (cga_tables(ctypes.byref(size)), size.value)
        elif self.target == "victim":
            if self.victim not in shared_state.HEAP_BUFFERS:
                raise ValueError(f"no HeapVictim named {self.victim!r} has its buffer yet")
            self.span = shared_state.HEAP_BUFFERS[self.victim]
        else:
            raise ValueError(f"parameter 'target' must be 'victim' or 'allocator-tables', got {self.target!r}")
        if not 1 <= self.count <= self.span[1]:
            raise ValueError("parameter 'bytes' must be 1 to the target's size")

    def fire(self):
        addr, size = self.span
        ctypes.memset(addr + self.rng.randrange(size - self.count + 1), 0x5A, self.count)


class DoubleFreer(_FaultNode):
    """Frees a block the HeapVictim named ``victim`` (another node's
    process) malloc'd and gave away, and at once frees it again: a double
    free of another node's block. Whether the damage lands in the owner or
    in this node is the container's doing."""

    fault = "double-free"

    def __init__(self, **kwargs):
        super().__init__("double_freer", **kwargs)
        self.victim = self.declare_parameter("victim", "heap_victim").value
        if not shared_state.DONATED_BLOCKS.get(self.victim):
            raise ValueError(f"no HeapVictim named {self.victim!r} has blocks to give away")

    def fire(self):
        block = shared_state.DONATED_BLOCKS[self.victim].pop()
        _libc.free(block)
        _libc.free(block)


class UseAfterFree(_FaultNode):
    """Frees a block the HeapVictim named ``victim`` (another node's
    process) malloc'd and gave away, then writes ``bytes`` bytes into it: a
    use after free of another node's block (the owner's allocator owns it
    again; it may already be the owner's next malloc). Whether the write
    lands or faults is the container's doing."""

    fault = "use-after-free"

    def __init__(self, **kwargs):
        super().__init__("use_after_free", **kwargs)
        self.victim = self.declare_parameter("victim", "heap_victim").value
        self.count = self.declare_parameter("bytes", 64).value
        if not shared_state.DONATED_BLOCKS.get(self.victim):
            raise ValueError(f"no HeapVictim named {self.victim!r} has blocks to give away")
        if not 1 <= self.count <= 64:
            raise ValueError("parameter 'bytes' must be 1 to 64 (the donated blocks' size)")

    def fire(self):
        block = shared_state.DONATED_BLOCKS[self.victim].pop()
        _libc.free(block)
        ctypes.memset(block, 0x5A, self.count)


class HeapOverflow(_FaultNode):
    """Overflows a 64-byte block of its own heap by ``bytes`` bytes (its
    neighbours and the allocator's metadata between them), then mallocs and
    frees blocks of random sizes, as a node goes on after such a bug.
    Whether it dies, and whether anything beyond its own heap is touched,
    is the container's doing."""

    fault = "heap-overflow"

    def __init__(self, **kwargs):
        super().__init__("heap_overflow", **kwargs)
        self.count = self.declare_parameter("bytes", 4096).value
        if not 1 <= self.count <= 1 << 20:
            raise ValueError("parameter 'bytes' must be 1 B to 1 MiB")

    def fire(self):
        blocks = [_libc.malloc(64) for _ in range(64)]
        ctypes.memset(blocks[self.rng.randrange(32)] + 64, 0x5A, self.count)
        for block in blocks:
            _libc.free(block)
        for _ in range(10_000):
            _libc.free(_libc.malloc(self.rng.randrange(16, 4096)))
