"""Python locks whose holder died: taken over, named, reported, repairable.

In isolated mode every node process runs in the container's one
interpreter, so a module-level ``threading.Lock`` (or RLock, Condition,
queue.Queue, a logging handler's lock) is shared by all of them. The
container replaces CPython's lock types with ones that record their
holder's process (isolated/pylocks.c, installed by isolated/boot.py before
``threading`` is first imported). When a node process dies holding one, the
next acquirer gets it -- within ``SLICE_MS`` of waiting -- and then:

- the container publishes a ComponentEvent REPAIRED (``repaired_state``
  ``"python-lock"``) naming the lock by what refers to it
  (``my_robot.calib.CALIB_LOCK``), the dead holder (node, pid, thread) and
  that what the lock guards may be half-updated;
- a repair callback the component registered for that lock runs, in the
  acquirer's thread, holding the lock, before ``acquire()`` returns: the
  place to put the guarded state back in order (as a robust mutex's
  EOWNERDEAD asks its locker to, before ``pthread_mutex_consistent``)::

      from cloneguard.container import locks

      CALIB_LOCK = threading.Lock()
      locks.on_dead_holder(CALIB_LOCK, lambda death: CALIB.reset())

In thread mode (one process) a holder cannot die alone: ``on_dead_holder``
is accepted and never called.
"""

from __future__ import annotations

import gc
import os
import sys
import threading
import types
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from . import processes, repairs, seams


@dataclass(frozen=True)
class DeadHolder:
    """What a repair callback is told: the lock, where it is referred to
    from, and who held it."""

    lock: object
    name: str  # e.g. "my_robot.calib.CALIB_LOCK"
    node: str  # the dead holder's node ("" if the container does not know it)
    pid: int
    tid: int


_callbacks: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def on_dead_holder(lock: object, callback: Callable[[DeadHolder], None]) -> None:
    """Call ``callback(DeadHolder)`` when ``lock`` is taken over from a
    holder whose process died (isolated mode), in the thread that then
    holds it, before its ``acquire()`` returns. One callback a lock; a later
    one replaces it."""
    _callbacks[lock] = callback


def _referrer_name(obj: object) -> str:
    """What refers to ``obj``: a module's global (``pkg.mod.NAME``), or an
    attribute of one (``pkg.mod.CONDITION._lock``, ``pkg.mod.Class.attr``);
    else, through the collector, an attribute of an object named so in
    turn; else its repr. Found only when needed (a takeover is rare).

    Modules are searched first, by their dicts: after a death with the GIL
    held the young objects are moved where gc.get_referrers does not look
    (interp.c), a recently imported module's dict among them."""
    modules = _modules()
    named = next((name for name, value in _module_names(modules) if value is obj), None)
    return named or _referrer_by_gc(obj, {id(m.__dict__): name for name, m in modules})


def _modules() -> list[tuple[str, types.ModuleType]]:
    modules = [(name, m) for name, m in list(sys.modules.items()) if m is not None and name != "__main__"]
    return modules + ([("__main__", sys.modules["__main__"])] if "__main__" in sys.modules else [])  # a script's last


def _module_names(modules: list[tuple[str, types.ModuleType]]) -> Iterator[tuple[str, object]]:
    """(name, value) of every module's globals (``pkg.mod.NAME``), then of
    the attributes of those that are neither modules nor plain values
    (``pkg.mod.OBJ.attr``)."""
    for name, module in modules:
        for key, value in list(vars(module).items()):
            yield f"{name}.{key}", value
    for name, module in modules:
        for key, value in list(vars(module).items()):
            attrs = getattr(value, "__dict__", None)
            if isinstance(attrs, (dict, types.MappingProxyType)) and not isinstance(value, types.ModuleType):
                for attr, v in list(attrs.items()):
                    yield f"{name}.{key}.{attr}", v


#: A python-lock stop request's key -> (how many modules there were when it
#: was looked for, the lock of that name or None).
_asked_for: dict[int, tuple[int, object]] = {}


def _is_asked_for(lock: object, key: int) -> bool:
    """pylocks.c's name hook, while a python-lock stop request names a lock
    (the test rig's, seams.py): is ``lock`` the one named so? Looked up once
    per key, again only while not found and modules were imported since."""
    seen = _asked_for.get(key)
    if seen is None or (seen[1] is None and seen[0] != len(sys.modules)):
        modules = _modules()
        target = next((v for name, v in _module_names(modules) if seams.stop_lock_key(name) == key), None)
        seen = _asked_for[key] = (len(sys.modules), target)
    return seen[1] is lock


def _referrer_by_gc(obj: object, modules: dict[int, str], depth: int = 3) -> str:
    for ref in gc.get_referrers(obj):
        if isinstance(ref, dict):
            key = next((k for k, v in ref.items() if v is obj), None)
            if key is None:
                continue
            if id(ref) in modules:
                return f"{modules[id(ref)]}.{key}"
            owners = [o for o in gc.get_referrers(ref) if getattr(o, "__dict__", None) is ref]
        else:  # 3.11 keeps an instance's attributes inline: the instance refers to it
            attrs = getattr(ref, "__dict__", None)
            key = next((k for k, v in attrs.items() if v is obj), None) if isinstance(attrs, dict) else None
            owners = [ref] if key is not None else []
        for owner in owners:
            if isinstance(owner, type):
                return f"{owner.__module__}.{owner.__qualname__}.{key}"
            named = _referrer_by_gc(owner, modules, depth - 1) if depth > 1 else ""
            if named and not named.startswith("<"):
                return f"{named}.{key}"
            return f"{type(owner).__module__}.{type(owner).__qualname__}.{key}"
    return repr(obj)


def _took_over(lock: object, pid: int, tid: int) -> None:
    """pylocks.c's hook, in the acquirer's thread, holding the lock."""
    unique_id, node = processes.node_of(pid)
    name = _referrer_name(lock)
    kind = "RLock" if "RLock" in type(lock).__name__ else "Lock"
    me = processes.who(os.getpid())
    repairs.record(
        repairs.PYTHON_LOCK,
        unique_id,
        f"the Python {kind} {name}, held by {node or 'a node process'} (pid {pid}, thread {tid}) when its process "
        f"died, was taken over by {me}; what it guards may be half-updated",
    )
    callback = _callbacks.get(lock)
    if callback is not None:
        callback(DeadHolder(lock, name, node, pid, tid))


def _stuck(lock: object, waited_s: float) -> None:
    """pylocks.c's other hook: a thread has waited this long, after a node
    process died, for a lock whose holder is not known (one that died
    between taking it and recording itself looks so): not taken over, said."""
    os.write(
        2,
        (
            f"cloneguard: {repairs.NOT_REPAIRED}{processes.who(os.getpid())} thread {threading.get_native_id()} has "
            f"waited {waited_s:.1f} s for the Python lock {_referrer_name(lock)}, whose holder is not known (it may "
            "have died taking it): not taken over\n"
        ).encode(errors="replace"),
    )


def installed() -> bool:
    """Are Python's lock types the ones that know their holder (isolated
    mode: boot.py installed them)?"""
    import _thread

    return type(_thread.allocate_lock()).__module__.endswith("._pylocks")


def activate() -> None:
    """The container: from now on, report takeovers and stuck waits."""
    from .isolated import _pylocks  # type: ignore[attr-defined]  # an extension module

    _pylocks.set_hooks(_took_over, _stuck, _is_asked_for)
