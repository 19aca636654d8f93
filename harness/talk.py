"""Talking to a user's nodes the way their own clients would: a service
call that returns its answer, an action goal with its feedback and result,
and a lifecycle node's transitions. ``System.call``, ``System.send_goal``,
``System.change_state`` and ``System.get_state`` are these (public:
docs/testing-your-nodes.md); each runs on the harness client's own node and
thread, so a test writes no rclpy of its own.

Every call has a timeout and raises ``HarnessTimeout`` (an
AssertionError) naming what did not happen: a service or action server not
offered, an answer or result that did not come.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from lifecycle_msgs.msg import State
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.action import ActionClient

from .client import ContainerClient, Recorder
from .errors import HarnessTimeout

if TYPE_CHECKING:
    from rclpy.client import Client
    from rclpy.task import Future

#: A lifecycle node's primary states, by their ids (lifecycle_msgs/State).
STATE_LABELS = {
    State.PRIMARY_STATE_UNKNOWN: "unknown",
    State.PRIMARY_STATE_UNCONFIGURED: "unconfigured",
    State.PRIMARY_STATE_INACTIVE: "inactive",
    State.PRIMARY_STATE_ACTIVE: "active",
    State.PRIMARY_STATE_FINALIZED: "finalized",
}

#: GetState changes nothing: sent again after this long unanswered (a request
#: sent before the harness matched a reloaded node's new server is lost).
GET_STATE_RESEND_S = 1.0
#: A ChangeState unanswered this long: get_state says whether it was made.
CHANGE_STATE_ASK_S = 1.0
#: The primary state each transition ends in (lifecycle_msgs/Transition).
TRANSITION_ENDS = {
    "configure": "inactive",
    "activate": "active",
    "deactivate": "inactive",
    "cleanup": "unconfigured",
    "shutdown": "finalized",
}


@dataclass
class GoalOutcome:
    """What an action server did with a goal: whether it accepted it, the
    feedback it sent, and, for an accepted goal, its final status
    (action_msgs/GoalStatus: 4 succeeded, 5 canceled, 6 aborted) and
    result. ``feedback`` is a Recorder of the feedback messages that
    reached the harness. Feedback is a volatile topic, as for any rclpy
    ActionClient: what the server published before it had discovered the
    harness's client is lost (send_goal waits until the harness has seen
    the server's feedback publisher, which narrows that window but cannot
    close it from this side). Feedback and result also travel apart (a
    topic and a service), so feedback can arrive after the result; wait
    for it with ``feedback.wait_for``. The result is never lost."""

    accepted: bool
    feedback: Recorder
    status: int = 0
    result: Any = None  # the action's Result message (ROS messages have no stubs)


class Talker:
    """Clients of a system's services and actions, made once per name and
    type, on the harness client's node (they go with it)."""

    def __init__(self, client: ContainerClient):
        self._client = client
        self._services: dict[tuple[str, type], Client] = {}
        self._actions: dict[tuple[str, type], ActionClient] = {}

    def call(
        self, srv_type: type, name: str, request: object, timeout: float, *, resend_after: float | None = None
    ) -> Any:
        """``request`` to service ``name``; its answer. ``resend_after``:
        as ContainerClient.call's, for a request that changes nothing."""
        key = (name, srv_type)
        if key not in self._services:
            self._services[key] = self._client.service_client(srv_type, name)
        return self._client.call(self._services[key], request, timeout, resend_after=resend_after)

    def send_goal(self, action_type: type, name: str, goal: object, timeout: float) -> GoalOutcome:
        """Send ``goal`` to action server ``name``; wait for its acceptance
        and, if accepted, its result: all within ``timeout``."""
        key = (name, action_type)
        if key not in self._actions:
            self._actions[key] = ActionClient(self._client.node, action_type, name)
        action = self._actions[key]
        deadline = time.monotonic() + timeout
        if not action.wait_for_server(timeout_sec=timeout):
            raise HarnessTimeout(f"action server {name} not offered within {timeout:.1f} s")
        feedback_topic = f"{name}/_action/feedback"
        while not self._client.node.count_publishers(feedback_topic):
            if time.monotonic() > deadline:
                raise HarnessTimeout(
                    f"{name} offers its services but no {feedback_topic} publisher within {timeout:.1f} s"
                )
            time.sleep(0.01)
        outcome = GoalOutcome(accepted=False, feedback=Recorder(f"feedback of a goal sent to {name}"))
        sent = self._on_client_thread(
            lambda: action.send_goal_async(goal, feedback_callback=lambda msg: outcome.feedback._add(msg.feedback)),
            timeout,
        )
        handle = _wait(sent, timeout, f"no answer to a goal sent to {name}")
        if not handle.accepted:
            return outcome
        outcome.accepted = True
        asked = self._on_client_thread(handle.get_result_async, timeout)
        done = _wait(asked, timeout, f"no result of an accepted goal of {name}")
        outcome.status, outcome.result = done.status, done.result
        return outcome

    def _on_client_thread(self, send: Callable[[], Future], timeout: float) -> Future:
        """``send()`` run on the harness client's spin thread, its future.
        rclpy 7.1's ActionClient sends a request before it records the
        future that waits for the answer, without a lock (rclpy issue
        1123): sent from another thread, an answer the spin thread takes
        in between is dropped ("Ignoring unexpected goal response") and the
        future never completes (seen 1 run in 4 against a thread-mode
        server, which answers at once). On the spin thread nothing runs in
        between."""
        return _wait(self._client.run_on_spin_thread(send), timeout, "the harness client's thread to send")

    def change_state(self, node: str, transition: str, timeout: float) -> bool:
        """Ask lifecycle node ``node`` (its full name) for ``transition``
        by its label (``configure``, ``activate``, ``deactivate``,
        ``cleanup``, ``shutdown``); whether the node made it.

        A request can be lost on its way (a reloaded node's new server not
        yet matched while its dead predecessor's still shows in the graph).
        A transition must not be asked for twice, so one unanswered for
        CHANGE_STATE_ASK_S is followed by get_state (which is resent until
        answered): in the transition's end state, it was made; in a
        transition state, it is under way (its answer went with the
        abandoned request: get_state again until a primary state); in the
        state it started from, the request was lost and is sent again."""
        request = ChangeState.Request()
        request.transition.label = transition
        deadline = time.monotonic() + timeout
        while True:
            try:
                asked = min(CHANGE_STATE_ASK_S, max(0.0, deadline - time.monotonic()))
                return bool(self.call(ChangeState, f"{node}/change_state", request, asked).success)
            except HarnessTimeout:
                if time.monotonic() >= deadline:
                    raise
            state = self.get_state(node, max(0.0, deadline - time.monotonic()))
            while state not in STATE_LABELS.values():  # "configuring", ...: under way
                state = self.get_state(node, max(0.0, deadline - time.monotonic()))
            if state == TRANSITION_ENDS.get(transition):
                return True

    def get_state(self, node: str, timeout: float) -> str:
        """Lifecycle node ``node``'s current state's label (``unconfigured``,
        ``inactive``, ``active``, ``finalized``, or a transition state's)."""
        state = self.call(
            GetState, f"{node}/get_state", GetState.Request(), timeout, resend_after=GET_STATE_RESEND_S
        ).current_state
        return state.label or STATE_LABELS.get(state.id, str(state.id))


def _wait(future: Future, timeout: float, what: str) -> Any:
    """The result of an rclpy future the client's thread completes."""
    done = threading.Event()
    future.add_done_callback(lambda _f: done.set())
    if not done.wait(timeout):
        future.cancel()
        raise HarnessTimeout(f"{what} within {timeout:.1f} s")
    return future.result()
