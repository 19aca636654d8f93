"""Container-owned intra-process state: the queue, the bus, the loan pool.

Deaths are real: a clone(CLONE_VM) child of the core takes the lock and is
SIGKILLed in the middle of a put or a take.
"""

import gc
import threading
import time

import pytest

from cloneguard.container import seams
from cloneguard.container.intra.bus import Bus, PublisherEntry, SubscriptionEntry
from cloneguard.container.intra.pool import MIN_BLOCK, LoanPool, size_class
from cloneguard.container.intra.queue import MessageQueue
from cloneguard.container.isolated.core import CloneCore


@pytest.fixture
def core():
    c = CloneCore()
    yield c
    c.close()


def test_queue_is_fifo_and_reports_when_it_was_empty():
    q = MessageQueue(3)
    assert q.put("a") is True  # empty before: wake the subscriber
    assert q.put("b") is False
    assert q.take_all() == ["a", "b"]
    assert len(q) == 0 and q.take_all() == []
    assert q.put("c") is True


def test_queue_keep_last_drops_the_oldest_and_counts_it():
    q = MessageQueue(2)
    for m in "abcde":
        q.put(m)
    assert q.take_all() == ["d", "e"]
    assert q.dropped == 3


def test_queue_holds_the_object_itself():
    q = MessageQueue(1)
    msg = object()
    q.put(msg)
    assert q.take_all()[0] is msg


def test_queue_rejects_a_zero_capacity():
    with pytest.raises(ValueError, match="at least 1"):
        MessageQueue(0)


def _die_inside(core, hook_name: str, action):
    """Run ``action`` in a child with the queue hook ``hook_name`` parking it
    inside the critical section; SIGKILL it there."""
    inside = threading.Event()

    def park(_q):
        inside.set()
        time.sleep(60)

    seams.arm(hook_name, park)
    try:
        child = core.spawn(action)
        assert inside.wait(10), "the child never reached the critical section"
        core.kill(child)
        assert core.wait(child, 10) is not None
    finally:
        seams.arm(hook_name, None)
    core.release(child)


def test_publisher_killed_mid_put_leaves_a_consistent_queue(core):
    repaired: list[MessageQueue] = []
    q = MessageQueue(4, on_repair=repaired.append)
    q.put("before")
    _die_inside(core, "queue_mid_put", lambda: q.put("torn"))
    # The next locker gets EOWNERDEAD: the slot written but never published
    # is not delivered, what was committed is.
    assert q.take_all() == ["before"]
    assert q.repairs == 1 and repaired == [q]
    assert q.put("after") is True and q.take_all() == ["after"]
    assert q.repairs == 1


def test_publisher_killed_mid_put_into_a_full_queue_loses_only_the_dropped_oldest(core):
    q = MessageQueue(2)
    q.put("old")
    q.put("new")
    _die_inside(core, "queue_mid_put", lambda: q.put("torn"))
    # The drop of the oldest was committed before the slot was reused.
    assert q.take_all() == ["new"]
    assert q.dropped == 1 and q.repairs == 1


def test_subscriber_killed_mid_take_leaves_the_messages_queued(core):
    q = MessageQueue(4)
    q.put("m1")
    q.put("m2")
    _die_inside(core, "queue_mid_take", q.take_all)
    assert q.take_all() == ["m1", "m2"]
    assert q.repairs == 1


def _entries(bus, owner, topic="/t", best_effort=False, reliable=True, msg_type=int):
    sub = SubscriptionEntry(owner, topic, msg_type, reliable, MessageQueue(2), wake=lambda: None)
    pub = PublisherEntry(owner, topic, msg_type, best_effort=best_effort, gid=bytes([owner]) * 16)
    bus.add_subscription(sub)
    bus.add_publisher(pub)
    return sub, pub


def test_bus_matches_by_topic_type_and_reliability():
    bus = Bus()
    sub, pub = _entries(bus, 1)
    assert bus.targets(pub) == [sub]
    assert bus.targets(PublisherEntry(2, "/other", int, False)) == []
    assert bus.targets(PublisherEntry(2, "/t", str, False)) == []
    # A RELIABLE subscription does not match a BEST_EFFORT publisher (as DDS).
    assert bus.targets(PublisherEntry(2, "/t", int, best_effort=True)) == []
    be_sub = SubscriptionEntry(3, "/t", int, False, MessageQueue(1), wake=lambda: None)
    bus.add_subscription(be_sub)
    assert bus.targets(PublisherEntry(2, "/t", int, best_effort=True)) == [be_sub]


def test_bus_forget_removes_one_loads_endpoints_and_gids():
    bus = Bus()
    sub1, pub1 = _entries(bus, 1)
    sub2, pub2 = _entries(bus, 2)
    assert bus.is_intra_publisher("/t", pub1.gid) and bus.is_intra_publisher("/t", pub2.gid)
    assert bus.forget(1) == 2
    assert bus.subscriptions("/t") == (sub2,)
    assert not bus.is_intra_publisher("/t", pub1.gid) and bus.is_intra_publisher("/t", pub2.gid)
    assert bus.forget(None) == 0 and bus.forget(1) == 0
    bus.remove(sub2)
    bus.remove(pub2)
    assert bus.subscriptions("/t") == () and not bus.is_intra_publisher("/t", pub2.gid)


def test_bus_lock_owner_death_is_recovered(core):
    bus = Bus()
    ready = threading.Event()

    def hold():
        bus._mutex.lock()
        ready.set()
        time.sleep(60)

    child = core.spawn(hold)
    assert ready.wait(10)
    core.kill(child)
    assert core.wait(child, 10) is not None
    core.release(child)
    _entries(bus, 1)
    assert bus.repairs == 1 and len(bus.subscriptions("/t")) == 1


# -- loan pool -----------------------------------------------------------------


def test_size_classes():
    assert size_class(0) == MIN_BLOCK and size_class(MIN_BLOCK) == MIN_BLOCK
    assert size_class(MIN_BLOCK + 1) == 2 * MIN_BLOCK
    assert size_class(16 << 20) == 16 << 20
    with pytest.raises(ValueError):
        size_class(-1)


def test_loan_is_writable_until_published_then_read_only():
    pool = LoanPool()
    loan = pool.loan(10)
    loan.buffer[:] = b"0123456789"
    loan.seal()
    with pytest.raises(ValueError, match="read-only"):
        _ = loan.buffer
    view = loan.view()
    assert bytes(view) == b"0123456789" and len(view) == 10
    with pytest.raises(TypeError):
        view[0] = 1


def test_a_released_loan_goes_back_and_is_reused():
    pool = LoanPool()
    loan = pool.loan(100_000)
    del loan
    gc.collect()
    assert pool.stats.returned == 1 and pool.idle_bytes == size_class(100_000)
    again = pool.loan(90_000)
    assert pool.stats.reused == 1 and pool.stats.blocks_mapped == 1 and pool.idle_bytes == 0
    del again


def test_pool_keeps_at_most_max_idle_bytes():
    pool = LoanPool(max_idle_bytes=MIN_BLOCK)
    loans = [pool.loan(10), pool.loan(10)]
    del loans
    gc.collect()
    assert pool.idle_bytes == MIN_BLOCK and pool.stats.unmapped == 1


def test_a_loan_outlives_the_child_that_filled_it(core):
    """The point of the pool: a subscriber can drop a message whose publisher
    was SIGKILLed, and the block returns, without the publisher's malloc."""
    pool = LoanPool()
    held = []
    filled = threading.Event()

    def publisher():
        loan = pool.loan(1 << 20)
        loan.buffer[:4] = b"abcd"
        loan.seal()
        held.append(loan)
        del loan  # a killed frame keeps its locals alive for good
        filled.set()
        time.sleep(60)

    child = core.spawn(publisher)
    assert filled.wait(10)
    core.kill(child)
    assert core.wait(child, 10) is not None
    core.release(child)
    assert bytes(held[0].view()[:4]) == b"abcd"
    held.clear()
    gc.collect()
    assert pool.stats.returned == 1
