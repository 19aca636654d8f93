"""The warm spare: the per-node profile's next process, made ahead.

A per-node load builds a DDS participant, and most of what such a load costs
beyond a thread-mode one is that participant (its first node took 8.1 ms, a
second node in the same Context 4.5 ms, measured; rmw_fastrtps makes a
Context's participant with its first node). So the host keeps one child made
ahead: its Context initialised and its participant made, held by a hidden
placeholder node (placeholder.py).
The next LoadNode it can serve is handed to it: it builds the node there,
then destroys the placeholder (the participant stays, the real node holds
it), and goes on as any per-node child. The host then makes the next spare.

A spare serves a load only when nothing about the load needs another
Context (``forward_global_arguments`` does: its Context takes the
container's ROS arguments) and nodes are not put in cgroups (each node's
process is born in its cgroup). Until it is handed a load it waits at its
gate off the GIL; asked to stop, it destroys its placeholder and Context and
ends. One that dies on its own is logged and replaced at the next load.

Every per-node process, spare or not, starts the same way (placeholder.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from .core import wait_for_go
from .placeholder import held_context, release_context

if TYPE_CHECKING:
    from collections.abc import Callable

    from rclpy.context import Context
    from rclpy.node import Node

    from ..options import NodeArguments
    from .host import _NodeProcess
    from .placeholder import Placeholder


@dataclass
class Spare:
    child: Any = None  # its Child, once spawned
    order: tuple | None = None  # (proc, cls, args): set before its go


def spare_target(
    spare: Spare,
    new_context: Callable[[], Context],
    build_and_spin: Callable[[_NodeProcess, Context, type[Node], NodeArguments, Placeholder | None], None],
) -> Callable[[], None]:
    """What a spare runs: ``held_context(new_context)``, then
    ``build_and_spin(proc, ctx, cls, args, placeholder)`` once handed a
    load, or its own clean-up if asked to stop first."""

    def run() -> None:
        ctx, placeholder = held_context(new_context)
        if wait_for_go():
            release_context(ctx, placeholder)
            return
        proc, cls, args = spare.order  # type: ignore[misc]  # set before its go
        build_and_spin(proc, ctx, cls, args, placeholder)

    return run


def serves(args: NodeArguments) -> bool:
    """Can a spare's Context (made with no ROS arguments) hold this load?"""
    return not args.forward_global_arguments
