"""The warm spare: the per-node profile's next process, made ahead.

A per-node load builds a DDS participant, and most of what such a load costs
beyond a thread-mode one is that participant (its first node took 8.1 ms, a
second node in the same Context 4.5 ms, measured; rmw_fastrtps makes a
Context's participant with its first node). So the host keeps one child made
ahead: its Context initialised and its participant made, held by a hidden
placeholder node (a leading underscore: ``ros2 node list`` leaves it out;
a bare rcl node, made off the GIL: ``Placeholder``).
The next LoadNode it can serve is handed to it: it builds the node there,
then destroys the placeholder (the participant stays, the real node holds
it), and goes on as any per-node child. The host then makes the next spare.

A spare serves a load only when nothing about the load needs another
Context (``forward_global_arguments`` does: its Context takes the
container's ROS arguments) and nodes are not put in cgroups (each node's
process is born in its cgroup). Until it is handed a load it waits at its
gate off the GIL; asked to stop, it destroys its placeholder and Context and
ends. One that dies on its own is logged and replaced at the next load.

Every per-node process, spare or not, starts the same way (``held_context``):
its participant is made by the placeholder, off the GIL, and the
placeholder outlives the construction, so that a failed construction's
half-built node is not the participant's last holder either: rclpy would
delete the participant with the GIL held, and Fast DDS can busy-wait in that
deletion (eProsima/Fast-DDS#6513), stopping every thread of the container.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

from ..intra._rclglue import ffi, lib
from .core import Child, wait_for_go

PLACEHOLDER_PREFIX = "_cloneguard_spare_"


@dataclass
class Spare:
    child: Child | None = None
    order: tuple | None = None       # (proc, cls, args): set before its go


class Placeholder:
    """A node process's placeholder (the spare's, and every per-node
    process's while its node is built): a bare rcl node (no rosout, no parameter or
    type-description services: no endpoints of its own), made and destroyed
    by cffi calls that release the GIL. Making it makes the participant, and
    rclpy would hold the GIL throughout: a Fast DDS lock that a dead node
    left taken (its payload pools are shared by every participant in the
    process) then blocked every Python thread of the container, not only
    this process (seen in deep runs)."""

    def __init__(self, ctx, name: str):
        err = ffi.new("char[]", lib.CGR_ERR_SIZE)
        out = ffi.new("rcl_node_t **")
        with ctx.handle:
            rc = lib.cgr_node_init(out, name.encode(), ffi.cast("rcl_context_t *", ctx.handle.pointer),
                                   err, lib.CGR_ERR_SIZE)
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


def held_context(new_context) -> tuple:
    """In a node's process: ``new_context()`` and the placeholder that makes
    and holds its participant; (ctx, placeholder)."""
    ctx = new_context()
    return ctx, Placeholder(ctx, f"{PLACEHOLDER_PREFIX}{os.getpid()}")


def release_context(ctx, placeholder: Placeholder | None = None) -> None:
    """In a node's process: its placeholder (which deletes the participant
    off the GIL when it is the last node), then the Context."""
    if placeholder is not None:
        placeholder.destroy_node()
    ctx.try_shutdown()
    ctx.destroy()


def spare_target(spare: Spare, new_context, build_and_spin):
    """What a spare runs: ``held_context(new_context)``, then
    ``build_and_spin(proc, ctx, cls, args, placeholder)`` once handed a
    load, or its own clean-up if asked to stop first."""
    def run():
        ctx, placeholder = held_context(new_context)
        if wait_for_go():
            release_context(ctx, placeholder)
            return
        proc, cls, args = spare.order
        build_and_spin(proc, ctx, cls, args, placeholder)
    return run


def serves(args) -> bool:
    """Can a spare's Context (made with no ROS arguments) hold this load?"""
    return not args.forward_global_arguments
