"""pybind11's registry of live instances, kept ahead of the node processes
(pybind11_registry.cpp: why a node killed while it rehashes ends the
container, and what this rests on).

The core calls ``keep_ahead`` on the container's threads: when it opens,
before every spawn, and after every collection of the collector; each is an
O(1) look unless fewer than HEADROOM inserts are left before the next
rehash."""

from __future__ import annotations

import functools
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from types import ModuleType

# Inserts a node process may make between two looks without rehashing.
# Each bucket is a pointer: the reserve costs 16 bytes per slot kept.
HEADROOM = 16384


def unavailable() -> str | None:
    """Why the registry cannot be kept ahead here, or None."""
    try:
        import cloneguard.container.isolated._pybind11_registry as _pybind11_registry  # an extension module
    except ImportError as e:
        return f"its module was not built ({e})"
    rclpy_module = sys.modules.get("rclpy._rclpy_pybind11")
    # Not loaded yet: rclpy will find the internals this module made under
    # the same key (INTERNALS_ID), if it is built for the same ABI.
    if rclpy_module is not None and not _pybind11_registry.knows_type(rclpy_module.Context):
        return (
            f"rclpy's pybind11 modules keep their instances in other internals than "
            f"{_pybind11_registry.INTERNALS_ID} (another pybind11 ABI)"
        )
    return None


def keep_ahead() -> bool:
    """Rehash now if a node process could soon have to; True if it did.
    Hold the GIL (any Python caller does). Only where ``unavailable()``
    is None: on every spawn, so the module is looked up once."""
    return bool(_module().keep_ahead(HEADROOM))


def state() -> tuple[int, int, int]:
    """(instances, buckets, inserts left before a rehash)."""
    n, buckets, left = _module().state()
    return int(n), int(buckets), int(left)


@functools.cache
def _module() -> ModuleType:
    import cloneguard.container.isolated._pybind11_registry as _pybind11_registry  # an extension module

    return _pybind11_registry
