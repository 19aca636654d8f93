"""The shared profile's rclpy Context lock survives a child killed holding it."""

import logging
import threading
import time
from typing import Any

import pytest
from ros_support import ros_nodes

from cloneguard.container.isolated.core import CloneCore
from cloneguard.container.isolated.host import _robust_context_lock

# What it logs with (it calls only warning()): Python's logging, which caplog reads.
LOG: Any = logging.getLogger("test")


@pytest.fixture
def context():
    with ros_nodes() as (_, executor):
        yield executor.context


def _kill_holding(core, lock) -> None:
    holding = threading.Event()

    def child():
        with lock:
            holding.set()
            time.sleep(60)

    proc = core.spawn(child)
    assert holding.wait(10)
    core.kill(proc)
    assert core.wait(proc, 10) is not None
    core.release(proc)


def test_context_ok_goes_on_after_a_child_died_holding_its_lock(context):
    _robust_context_lock(context, LOG)
    core = CloneCore()
    try:
        _kill_holding(core, context._lock)
        # rclpy's own lock would block here for good; the robust one recovers.
        assert context.ok() is True
        assert context.ok() is True
    finally:
        core.close()


def test_a_context_without_the_expected_lock_is_left_alone(context, caplog):
    context._lock = threading.RLock()  # not what rclpy 7.1 has
    with caplog.at_level(logging.WARNING):
        _robust_context_lock(context, LOG)
    assert isinstance(context._lock, type(threading.RLock()))
    assert "stays non-robust" in caplog.text
