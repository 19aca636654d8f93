"""A LoadNode of faults::SlowConstructor, sent from a thread of the test."""

import threading
import time

from cloneguard.faults import PACKAGE as TESTRIG


class SlowLoad:
    """Sends the load; returns once the node is in the graph (its
    constructor is sleeping)."""

    def __init__(self, client, seconds: float, timeout: float = 30.0):
        self._answers: list[object] = []
        self._thread = threading.Thread(
            target=lambda: self._answers.append(
                client.load(TESTRIG, "faults::SlowConstructor", parameters={"seconds": seconds}, timeout=timeout)
            )
        )
        self._thread.start()
        deadline = time.monotonic() + 10
        while "slow" not in client.node.get_node_names():
            assert time.monotonic() < deadline, "the slow constructor never started"
            time.sleep(0.05)

    def waiting(self) -> bool:
        """Is the LoadNode still unanswered?"""
        return self._thread.is_alive()

    def answer(self, timeout: float = 30.0):
        self._thread.join(timeout)
        assert self._answers, f"no answer within {timeout:g} s"
        return self._answers[0]
