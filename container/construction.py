"""Build a component's node from its class and validated arguments."""

from __future__ import annotations

from typing import TYPE_CHECKING

from rclpy.logging import LoggingSeverity
from rclpy.node import Node

from . import intra
from ._rclglue import ffi, lib
from .options import LoadError, NodeArguments

if TYPE_CHECKING:
    from rclpy.context import Context


def construct(cls: type[Node], args: NodeArguments, context: Context, owner: int) -> Node:
    """Instantiate ``cls`` for load ``owner`` (its unique_id); any failure
    becomes a :class:`LoadError`, and whatever node the constructor had
    already made is destroyed (it leaves no trace in the ROS graph).
    Intra-process endpoints the node creates follow its
    ``use_intra_process_comms`` and belong to ``owner``."""
    try:
        with intra.api.constructing(owner, args.use_intra_process_comms):
            node = cls(**args.node_kwargs(context))
    except BaseException as exc:  # SystemExit too: the component's failure, not ours
        _destroy_half_built(exc)
        # Same wording as rclcpp_components for a throwing constructor.
        raise LoadError(f"Component constructor threw an exception: {type(exc).__name__}: {exc}") from None
    if not isinstance(node, Node):  # a class whose __new__ returns something else
        raise LoadError(f"Component {cls.__qualname__} did not produce an rclpy Node")
    intra.api.adopt(node, owner, args.use_intra_process_comms)
    if args.log_level:
        node.get_logger().set_level(LoggingSeverity(args.log_level))
    return node


def _destroy_half_built(exc: BaseException) -> None:
    """A constructor that raised after ``Node.__init__`` had made the node
    (a publisher made, then a bad parameter) leaves it alive: it is still a
    local (``self``) of the frames the exception went through. Destroy every
    Node found there."""
    seen: list[Node] = []
    tb = exc.__traceback__
    while tb is not None:
        for value in tb.tb_frame.f_locals.values():
            if isinstance(value, Node) and not any(value is s for s in seen):
                seen.append(value)
        tb = tb.tb_next
    for node in seen:
        try:
            destroy(node)
        except Exception:  # half made: destroy what can be
            pass


def destroy(node: Node) -> None:
    """Destroy a node the container built, with what ``Node.destroy_node``
    does not know about: its intra-process endpoints, its waitables (action
    servers and clients), a lifecycle node's state machine, and its type
    description service. The node is in no executor's wait any more.

    Each of these holds the rcl node (and so its Context and, in a node's
    own process, the DDS participant and its threads) until the garbage
    collector frees it: a node left so stays in the ROS graph after its
    unload, and its process never ends (it was SIGKILLed after 500 ms, and
    its participant left in memory)."""
    intra.api.destroy_endpoints(node)
    _finish_type_description_service(node)
    if hasattr(node, "_type_description_service"):
        node.destroy_node()
    else:
        _destroy_half_made(node)
    _destroy_waitables(node)
    _destroy_state_machine(node)


def _destroy_waitables(node: Node) -> None:
    """What rclpy 7.1's ``destroy_node`` leaves on the node: it destroys
    its publishers' and subscriptions' event handlers, not the other
    waitables. An ``ActionServer`` or ``ActionClient`` keeps its rcl action
    handle, which holds the rcl node. A waitable with no ``destroy`` (a
    user's own: rclpy's base class has none) is only taken off the node."""
    for waitable in list(node.waitables):
        destroy_waitable = getattr(waitable, "destroy", None)
        if destroy_waitable is not None:
            destroy_waitable()
        if any(w is waitable for w in node.waitables):  # destroy() took it off, or not
            node.remove_waitable(waitable)


def _destroy_state_machine(node: Node) -> None:
    """An ``rclpy.lifecycle.LifecycleNode`` keeps an rcl lifecycle state
    machine that holds the rcl node; rclpy 7.1 never destroys it (its
    services, which ``destroy_node`` does destroy, are the machine's)."""
    machine = getattr(node, "_state_machine", None)
    if machine is not None and hasattr(machine, "destroy_when_not_in_use"):
        machine.destroy_when_not_in_use()


def _destroy_half_made(node: Node) -> None:
    """``Node.destroy_node`` for a node whose ``Node.__init__`` raised before
    it made the type description service, its last step (a built-in
    parameter of the wrong type: ``use_sim_time`` as a string, say). rclpy
    7.1's destroy_node destroys the node's entities, then stops at that
    service's ``destroy()`` with an AttributeError, before the rcl node: it
    stayed alive with its /rosout publisher registered and, as the last
    node of a per-node Context, kept that Context's DDS participant and its
    threads (the node's process then never ended)."""
    try:
        node.destroy_node()
    except AttributeError:
        if hasattr(node, "_type_description_service"):
            raise
    handle = getattr(node, "_Node__node", None)  # None: rcl_node_init itself failed
    if handle is not None:
        handle.destroy_when_not_in_use()


def _finish_type_description_service(node: Node) -> None:
    """rclpy 7.1 (rclpy/src/rclpy/type_description_service.cpp) keeps each
    node's ~/get_type_description rcl_service_t in a shared_ptr with no
    deleter, so rcl_service_fini never runs: its DDS reader and writer live
    on after destroy_node(), visible in the graph, ~0.1 MiB each (and every
    later endpoint pairs against them, so creating nodes slows down). The
    last node of a Context hides it (the participant goes), not a container
    that keeps its Context. rclcpp had the same bug (fixed by a deleter)."""
    service = getattr(getattr(node, "_type_description_service", None), "_type_description_srv", None)
    if service is None:
        return
    err = ffi.new("char[]", lib.CGR_ERR_SIZE)
    with node.handle, service.impl:
        rc = lib.cgr_service_fini(
            ffi.cast("rcl_service_t *", service.impl.pointer),
            ffi.cast("rcl_node_t *", node.handle.pointer),
            err,
            lib.CGR_ERR_SIZE,
        )
    if rc != 0:
        why = ffi.string(err).decode(errors="replace")
        node.get_logger().warning(f"finalizing ~/get_type_description failed: {why}")
