"""A dead node's memory given back: the plain data only it could reach.

A node process that dies leaves its node, executor and (per-node) Context in
memory: destroying them could block on a lock it held (host.py). Whatever
they hold stays with them, so a node that leaked until the memory watch
ended it would leave its container at its limit. This lets go of the part
that is plain data and that nothing alive can reach, and keeps the rest.

**What is let go of.** Lists, dicts, sets and bytearrays (those exact
types) that only the dead node's objects reach are emptied; what they held
is then freed by reference counting unless something else holds it.
Emptying one runs no code but the allocator's. Objects of any other type
(instances of classes, rclpy's handles, functions, generators, ...) are
never freed: their end could run code (``__del__``, a C++ destructor taking
a lock the dead process held), so each one found only the dead node
reaches is kept referenced for good (``Released.kept``). An instance's own
``__dict__`` is never emptied (the object stays whole).

**Only it could reach: the proof, by counting references.** From the roots
(the dead node and its executor: the container never uses them again) every
object they lead to is found with ``gc.get_referents`` (what the garbage
collector follows), stopping at modules, classes and modules' globals.
For each object found, its references from objects found (and, certain
ones only, from the dead task's frames: interp.c ``cg_dead_frame_refs``)
are subtracted from its reference count. Any left over come from somewhere
else: from something alive, or from something not followed (C++ holding a
Python object, the dead task's C stack, a stack slot not known to be one).
Such an object, and everything it leads to, is *alive* and untouched,
except through a root: the roots are dead by declaration, whatever still
refers to them (the container's bookkeeping, the dead node's timers and
services, whose callbacks are bound to it, its executor's generator on the
dead task's stack), since no code of the dead node ever runs again. The
rest is reached only from the dead. A count that comes out below zero means
a reference was counted twice: then nothing is let go of (``Refused``).

**What the dead task may have been changing is kept whole.** A task
changes Python objects only holding the GIL, and then those the instruction
it was running works on: the inputs of its innermost frame's call (the top
of its value stack, where its bytecode says: stack_depth.py), or, at any
other instruction, anything on that stack, and any word of a frame being
set up or torn down. After a death holding the GIL, whatever those words
may point at (``maybe``) is neither followed (reading a list killed
half-way through a resize would follow a freed block) nor emptied, and
what it holds counts as alive: a list the dying task was appending to
keeps what it held. This holds for a death inside an allocator too (the
block being allocated was not handed to anyone yet; a list being resized
is an input of the call resizing it). A node process that died of a fault
of its own may have torn anything: then nothing is let go of.

Freeing from the container hands a dead node's blocks back to its slot
(allocguard.c, pyalloc.c); the host then drains them at once
(``CloneCore.give_back``: the dead process's context was held out of the
pool since its death, so no other process has taken the slot), so that
the slot's emptied Python object pools
and jemalloc's freed extents go back to the kernel now; glibc's mmapped
blocks (a big bytearray) go back at their free. What is not given
back: memory in the dead node's arenas that nothing points to (a native
leak); the blocks of a quarantined arena (handed to it for good); under
glibc, small blocks of the slot's arenas until the next process in the slot
drains them; data an object's attribute holds directly rather than in a
container (a big ``str``); the dead node's own objects of other types (its
node, executor, DDS participant); whatever alive code reaches.
"""

from __future__ import annotations

import ctypes
import gc
import sys
import types
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .stack_depth import call_stack

if TYPE_CHECKING:
    from .core import DeadFrames

# Emptied when only the dead reach them.
EMPTIED = frozenset({list, dict, set, bytearray})
# Freed when nothing holds them: their end runs no code.
PLAIN = EMPTIED | {tuple, frozenset, bytes, str, int, float, complex, bool, type(None)}
# Refer to nothing: never followed, never counted (freed or not by their holders).
LEAVES = frozenset({bytes, str, int, float, complex, bool, type(None)})
# Stop there (a bound on the time and memory one examination may take).
MAX_OBJECTS = 2_000_000
# References the count loop itself holds to the object it counts: the
# table's, the loop variable's, getrefcount's argument.
_COUNTING_REFS = 3


class Refused(Exception):
    """Nothing was let go of, and why."""


@dataclass
class Released:
    """What an examination found and let go of."""

    found: int = 0  # objects followed from the roots
    alive: int = 0  # ... that something alive, or not known, reaches
    suspect: int = 0  # ... that the dead task may have been changing
    emptied: int = 0  # lists, dicts, sets, bytearrays emptied
    kept: list = field(default_factory=list, repr=False)  # the dead-only objects of other types


def _boundary(x: object) -> bool:
    """Shared by the whole interpreter: never followed."""
    t = type(x)
    return t is types.ModuleType or isinstance(x, type) or (t is dict and "__builtins__" in x and "__name__" in x)  # type: ignore[operator]


def _find(roots: Iterable[object], suspect: set[int]) -> tuple[dict[int, object], set[int]]:
    """Every object the roots lead to (by id), and those whose references
    were followed (not a boundary, not suspect)."""
    found: dict[int, object] = {}
    followed: set[int] = set()
    stack = list(roots)
    while stack:
        x = stack.pop()
        i = id(x)
        if i in found:
            continue
        found[i] = x
        if len(found) > MAX_OBJECTS:
            raise Refused(f"more than {MAX_OBJECTS} objects to examine")
        if _boundary(x) or i in suspect:
            continue
        followed.add(i)
        stack.extend(r for r in gc.get_referents(x) if type(r) not in LEAVES and id(r) not in found)
    return found, followed


_STANDARD = (types.GetSetDescriptorType, types.MemberDescriptorType)


def _own_dicts(x: object) -> list[int]:
    """The dicts an object of another type refers to that may be its own
    ``__dict__`` (never emptied): the one its standard descriptor returns
    (C code: none of its class's runs); every dict it refers to where its
    class has another kind of ``__dict__``, or none. (A 3.11 class's
    instance without a ``__dict__`` made refers to its attributes' values
    directly: a dict among them is data.)"""
    dicts = [id(r) for r in gc.get_referents(x) if type(r) is dict]
    if not dicts:
        return []
    for klass in type(x).__mro__:
        d = klass.__dict__.get("__dict__")
        if d is not None:
            return [id(d.__get__(x, type(x)))] if type(d) in _STANDARD else dicts
    return dicts


def _inner_references(found: dict[int, object], followed: set[int], known: Iterable[int]) -> dict[int, int]:
    """How many references each found object has from those followed and
    from the dead task's frames. (A function of its own: no variable of
    the caller is left holding an object when the counts are compared.)"""
    inner: dict[int, int] = {}
    for i in followed:
        for j in map(id, gc.get_referents(found[i])):
            if j in found:
                inner[j] = inner.get(j, 0) + 1
    for w in known:
        if w in found:
            inner[w] = inner.get(w, 0) + 1
    return inner


def examine(roots: list[object], known: Iterable[int], maybe: Iterable[int], torn: bool) -> tuple[Released, list]:
    """Which objects only the roots reach: (what was found, the containers
    to empty). ``known``/``maybe``: the dead task's frames' references
    (addresses), certain and possible. ``torn``: it died holding the GIL."""
    suspect = set(maybe) if torn else set()
    found, followed = _find(roots, suspect)
    root_ids = set(map(id, roots))
    inner = _inner_references(found, followed, known)
    seeds = [i for i in suspect if i in found and i not in root_ids]
    for i in list(found):
        if i in root_ids:
            continue
        x = found[i]
        outer = sys.getrefcount(x) - _COUNTING_REFS - inner.get(i, 0)
        del x
        if outer < 0:
            raise Refused(f"an object's references counted more than it has ({outer}): nothing is let go of")
        if outer:
            seeds.append(i)
    alive: set[int] = set()
    while seeds:
        i = seeds.pop()
        if i in alive or i in root_ids:  # dead, whoever still refers to them
            continue
        alive.add(i)
        if i in followed:
            seeds.extend(j for j in map(id, gc.get_referents(found[i])) if j in found and j not in alive)
    protected = set()
    for i in followed:
        if type(found[i]) not in PLAIN:
            protected.update(_own_dicts(found[i]))
    dead = [found[i] for i in found if i not in alive and i not in root_ids]
    kept = [x for x in dead if type(x) not in PLAIN]
    result = Released(found=len(found), alive=len(alive), suspect=len(suspect & found.keys()), kept=kept)
    empty = [x for x in dead if type(x) in EMPTIED and id(x) not in protected]
    return result, empty


def frame_words(frames: DeadFrames) -> tuple[list[int], list[int]]:
    """The dead task's frames' words: (references for certain, maybe),
    its running frame's value stack read by its bytecode (stack_depth.py)."""
    known, maybe = list(frames.known), list(frames.maybe)
    if frames.running is not None:
        code_address, unit, words = frames.running
        code = ctypes.cast(code_address, ctypes.py_object).value  # its frame holds it: interp.c checked its type
        certain, possible = call_stack(code, unit, words)
        known += [w for w in certain if w]
        maybe += [w for w in possible if w]
    return known, maybe


def release(roots: list[object], frames: DeadFrames, torn: bool) -> Released:
    """Empty the containers only the roots reach (``examine``); the kept
    objects are in the result, which the caller holds for good."""
    result, empty = examine(roots, *frame_words(frames), torn)
    for x in empty:
        try:
            x.clear()  # type: ignore[attr-defined]
        except BufferError:  # a bytearray something still views
            continue
        result.emptied += 1
    return result
