"""Demo component: a service that answers with what it was sent.

``~/echo`` (cloneguard_interfaces/srv/Echo) returns the request's text, the
number of requests served and the pid of the process that served it, which
is how a caller sees which process a node runs in.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING

from cloneguard_interfaces.srv import Echo
from rclpy.node import Node

if TYPE_CHECKING:
    from typing import Any


class EchoService(Node):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("echo", **kwargs)
        self._served = 0
        self._srv = self.create_service(Echo, "~/echo", self._on_request)

    def _on_request(self, request: Echo.Request, response: Echo.Response) -> Echo.Response:
        self._served += 1
        response.data = request.data
        response.served = self._served
        response.pid = os.getpid()
        return response
