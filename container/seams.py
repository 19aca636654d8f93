"""The one seam through which the test rig reaches into the container.

Fault injection needs three things inside the product: a LoadNode extra
argument that drops the node's LOADED event (a lost event), a call made
while an intra-process queue operation holds its lock (to die right there),
and a progress-board write left half-done. All three are here, and all are
off unless the test rig is installed: the cloneguard-testrig distribution
declares itself in the entry-point group ``cloneguard.test_rig``. A
production install has no test rig, so nothing can switch them on; the
extra argument is then an unknown one, ignored as upstream ignores those.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from importlib.metadata import entry_points

RIG_GROUP = "cloneguard.test_rig"
#: LoadNode extra argument (bool): the node loads, its LOADED event is not sent.
DROP_LOADED_EVENT = "cloneguard.fault.drop_loaded_event"

# Called with the queue while a put holds its lock, after the slot was
# written and before it is published; and while a take holds it, after the
# messages were read and before the commit. Set only through arm().
queue_mid_put: Callable[[object], None] | None = None
queue_mid_take: Callable[[object], None] | None = None


@functools.cache
def enabled() -> bool:
    """Whether the test rig is installed beside the product."""
    return any(True for _ in entry_points(group=RIG_GROUP))


def require(what: str) -> None:
    if not enabled():
        raise RuntimeError(f"{what} is fault injection: it needs the test rig (cloneguard-testrig) installed")


def arm(name: str, hook: Callable[[object], None] | None) -> None:
    """Set (or, with None, clear) ``queue_mid_put`` or ``queue_mid_take``."""
    if name not in ("queue_mid_put", "queue_mid_take"):
        raise ValueError(f"no seam called {name!r}")
    if hook is not None:
        require(name)
    globals()[name] = hook
