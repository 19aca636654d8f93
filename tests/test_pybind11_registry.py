"""pybind11's registry of live instances is rehashed by the container, never
by a node process (container/isolated/pybind11_registry.cpp: a node killed
in the middle of a rehash lost instances, and the container ended at the
next free of one).

rclpy's Clock handles stand for what a node makes: each is a pybind11
instance, inserted into the registry when made."""

from __future__ import annotations

import pytest
import rclpy._rclpy_pybind11 as _rclpy

from cloneguard.container.isolated import pybind11_registry
from cloneguard.container.isolated.assumptions import IsolationUnavailable
from cloneguard.container.isolated.core import CloneCore


def _make_in_a_child(core: CloneCore, count: int) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """The registry's state in a child before and after it made ``count``
    instances (dropped before it ends)."""
    seen: dict = {}

    def target() -> None:
        before = pybind11_registry.state()
        made = [_rclpy.Clock(_rclpy.ClockType.STEADY_TIME) for _ in range(count)]
        seen["states"] = (before, pybind11_registry.state())
        del made

    child = core.spawn(target)
    death = core.wait(child, 30)
    assert death is not None and death.exit_code == 0, death
    return seen["states"]


def test_it_shares_rclpys_registry():
    assert pybind11_registry.unavailable() is None
    import cloneguard.container.isolated._pybind11_registry as _pybind11_registry  # an extension module

    assert _pybind11_registry.knows_type(_rclpy.Context)
    clock = _rclpy.Clock(_rclpy.ClockType.STEADY_TIME)
    n = pybind11_registry.state()[0]
    del clock
    assert pybind11_registry.state()[0] == n - 1


def test_a_child_never_rehashes_it():
    with CloneCore() as core:
        assert core.mitigations.pybind11_ahead
        count = pybind11_registry.HEADROOM // 2
        before, after = _make_in_a_child(core, count)
        assert before[2] >= pybind11_registry.HEADROOM, before
        assert after[0] >= before[0] + count
        assert after[1] == before[1], f"the child rehashed: {before} -> {after}"
        # The next spawn (a container thread) restores the headroom.
        before, _ = _make_in_a_child(core, 1)
        assert before[2] >= pybind11_registry.HEADROOM, before


def test_without_it_a_child_rehashes():
    with CloneCore(pybind11_ahead=False) as core:
        left = pybind11_registry.state()[2]
        before, after = _make_in_a_child(core, left + 1)
        assert after[1] > before[1], f"no rehash: {before} -> {after}"


def test_required_where_it_cannot_work_is_refused(monkeypatch):
    monkeypatch.setattr(pybind11_registry, "unavailable", lambda: "another pybind11 ABI")
    with pytest.raises(IsolationUnavailable, match="cannot be kept ahead: another pybind11 ABI"):
        CloneCore(pybind11_ahead=True)
