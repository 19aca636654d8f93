"""A node process's Context and the placeholder that holds its participant.

Every per-node process, the warm spare's (spare.py) or not, starts the same
way (``held_context``): its Context, and a hidden placeholder node (a
leading underscore: ``ros2 node list`` leaves it out) whose making makes
the Context's DDS participant, off the GIL. The placeholder outlives the
construction, so that a failed construction's half-built node is not the
participant's last holder either: rclpy would delete the participant with
the GIL held, and Fast DDS can busy-wait in that deletion
(eProsima/Fast-DDS#6513), stopping every thread of the container.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from .._rclglue import ffi, lib

if TYPE_CHECKING:
    from collections.abc import Callable

    from rclpy.context import Context

PLACEHOLDER_PREFIX = "_cloneguard_spare_"


class Placeholder:
    """A node process's placeholder (the spare's, and every per-node
    process's while its node is built): a bare rcl node (no rosout, no parameter or
    type-description services: no endpoints of its own), made and destroyed
    by cffi calls that release the GIL. Making it makes the participant, and
    rclpy would hold the GIL throughout: a Fast DDS lock that a dead node
    left taken (its payload pools are shared by every participant in the
    process) then blocked every Python thread of the container, not only
    this process (seen in deep runs)."""

    def __init__(self, ctx: Context, name: str) -> None:
        err = ffi.new("char[]", lib.CGR_ERR_SIZE)
        out = ffi.new("rcl_node_t **")
        # rclpy types Context.handle as an Optional ContextHandle, a protocol without .pointer: an
        # initialised Context's is the pybind11 handle, which has it.
        with ctx.handle:  # type: ignore[union-attr]
            rc = lib.cgr_node_init(
                out,
                name.encode(),
                ffi.cast("rcl_context_t *", ctx.handle.pointer),  # type: ignore[union-attr]
                err,
                lib.CGR_ERR_SIZE,
            )
        if rc != 0:
            raise RuntimeError(ffi.string(err).decode(errors="replace"))
        self._node = out[0]

    def destroy_node(self) -> None:
        node, self._node = self._node, None
        if node is None:
            return
        err = ffi.new("char[]", lib.CGR_ERR_SIZE)
        if lib.cgr_node_fini(node, err, lib.CGR_ERR_SIZE) != 0:
            raise RuntimeError(ffi.string(err).decode(errors="replace"))


def held_context(new_context: Callable[[], Context]) -> tuple[Context, Placeholder]:
    """In a node's process: ``new_context()`` and the placeholder that makes
    and holds its participant; (ctx, placeholder)."""
    ctx = new_context()
    return ctx, Placeholder(ctx, f"{PLACEHOLDER_PREFIX}{os.getpid()}")


def release_context(ctx: Context, placeholder: Placeholder | None = None) -> None:
    """In a node's process: its placeholder (which deletes the participant
    off the GIL when it is the last node), then the Context."""
    if placeholder is not None:
        placeholder.destroy_node()
    ctx.try_shutdown()
    ctx.destroy()
