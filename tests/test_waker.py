"""cloneguard.container.intra's wakers: a post wakes the guard condition's executor, and
a closed waker stays safe for the publishers that still hold it."""

import threading

import pytest
from ros_support import ros_nodes

from cloneguard.container._rclglue import ffi
from cloneguard.container.intra.waker import Waker


@pytest.fixture
def node():
    with ros_nodes("waker_node") as (nodes, executor):
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        yield nodes[0]
        executor.shutdown()
        spinner.join(5)


class Wakes:
    def __init__(self):
        self.count, self.cond = 0, threading.Condition()

    def __call__(self):
        with self.cond:
            self.count += 1
            self.cond.notify_all()

    def wait_for(self, n, timeout=10.0):
        with self.cond:
            return self.cond.wait_for(lambda: self.count >= n, timeout)


def _block(waker: Waker) -> int:
    return int(ffi.cast("uintptr_t", waker._w))


def test_a_post_runs_the_guard_conditions_callback(node):
    wakes = Wakes()
    gc = node.create_guard_condition(wakes)
    waker = Waker()
    try:
        token = waker.add(gc)
        waker.post(token)
        assert wakes.wait_for(1)
        waker.remove(token)
    finally:
        assert waker.close()
        node.destroy_guard_condition(gc)


def test_a_late_post_to_a_closed_waker_lands_in_a_waker_and_wakes_nothing_it_should_not(node):
    old = Waker()
    old_token = old.add(node.create_guard_condition(lambda: None))
    assert old.close()
    # The next waker reuses the closed block: the memory a late post hits is
    # still a waker, never freed memory.
    wakes = Wakes()
    gc = node.create_guard_condition(wakes)
    new = Waker()
    try:
        assert _block(new) == _block(old)
        token = new.add(gc)
        # A stale remove through the old handle must not empty the new
        # waker's table (the same slot index, another subscription).
        assert token == old_token
        old.remove(old_token)
        old.post(old_token)  # late post from a publisher: one spurious wake at most
        new.post(token)
        assert wakes.wait_for(1)
    finally:
        assert new.close()
        node.destroy_guard_condition(gc)


def test_a_waker_in_use_is_never_handed_out_again():
    first, second = Waker(), Waker()
    try:
        assert _block(first) != _block(second)
    finally:
        assert first.close() and second.close()
