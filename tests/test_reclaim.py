"""What a dead node's objects let go of (container/isolated/reclaim.py) and
how a running frame's stack is read (stack_depth.py): real objects and real
reference counts, in this process (the container's own use is in
test_reclaim_container.py)."""

from __future__ import annotations

import dis
import gc
import sys
import types

import pytest

from cloneguard.container.isolated import reclaim
from cloneguard.container.isolated.core import DeadFrames
from cloneguard.container.isolated.stack_depth import call_stack, depths

NO_FRAMES = DeadFrames(known=[], maybe=[], running=None)
SHARED_BY_THE_MODULE: list = [bytearray(16)]


class Node(types.SimpleNamespace):
    """A dead node's object: an instance of a class (kept, never emptied),
    with any attribute."""


class Finalized:
    ended = 0

    def __del__(self):
        Finalized.ended += 1


def _dead_node() -> Node:
    node = Node()
    node.cache = [bytearray(1 << 20) for _ in range(4)]
    node.index = {"a": [b"x" * 100], "b": {1, 2}}
    node.blob = bytearray(1 << 20)
    return node


def test_plain_data_only_the_dead_reach_is_emptied_and_its_holders_kept():
    node = _dead_node()
    items = list(node.cache)  # one more reference each: alive
    done = reclaim.release([node], NO_FRAMES, torn=False)
    assert node.cache == [] and node.index == {} and node.blob == bytearray()
    assert all(len(b) == 1 << 20 for b in items)  # what something else holds stays whole
    assert done.emptied >= 3 and done.found >= 5
    assert vars(node).keys() == {"cache", "index", "blob"}  # the node itself untouched


def test_what_something_alive_reaches_is_untouched():
    node = _dead_node()
    alive = node.cache  # a live holder of the list
    node.shared = SHARED_BY_THE_MODULE
    reclaim.release([node], NO_FRAMES, torn=False)
    assert len(alive) == 4 and all(len(b) == 1 << 20 for b in alive)
    assert len(SHARED_BY_THE_MODULE) == 1 and len(SHARED_BY_THE_MODULE[0]) == 16
    assert node.index == {}  # what only it reached is emptied all the same


def test_objects_whose_end_runs_code_are_kept_not_ended():
    node = Node()
    node.tasks = [Finalized(), Finalized()]
    before = Finalized.ended
    done = reclaim.release([node], NO_FRAMES, torn=False)
    assert node.tasks == [] and Finalized.ended == before
    assert sum(type(x) is Finalized for x in done.kept) == 2
    del done
    gc.collect()
    assert Finalized.ended == before + 2  # held by the result, and only by it


def test_an_instance_dict_is_never_emptied():
    node = Node()
    node.__dict__["data"] = [1, 2, 3]  # a materialised __dict__
    inner = Node()
    inner.values = [4]
    vars(inner)  # materialised too
    node.inner = inner
    del inner  # only the dead node reaches it now
    reclaim.release([node], NO_FRAMES, torn=False)
    assert set(vars(node)) == {"data", "inner"} and set(vars(node.inner)) == {"values"}
    assert node.data == [] and node.inner.values == []


class Plain:
    """A class of 3.11 whose instances hold their attributes without a
    ``__dict__`` object until one is asked for."""

    def __init__(self):
        self.cache = {"k": [bytearray(1 << 20)]}


def test_a_dict_held_by_an_attribute_is_data_not_the_instances_own():
    node = Plain()
    reclaim.release([node], NO_FRAMES, torn=False)
    assert node.cache == {} and set(vars(node)) == {"cache"}


def test_a_reference_from_the_dead_frames_counts_as_the_deads():
    node = _dead_node()
    frame_locals = [node.index]  # stands in for a dead frame's local: not found from the root
    certain = DeadFrames(known=[id(node.index)], maybe=[], running=None)
    reclaim.release([node], certain, torn=False)
    assert frame_locals[0] == {}


def test_a_reference_counted_twice_refuses_and_changes_nothing():
    node = _dead_node()
    twice = DeadFrames(known=[id(node.cache), id(node.cache)], maybe=[], running=None)
    with pytest.raises(reclaim.Refused, match="counted more than it has"):
        reclaim.release([node], twice, torn=False)
    assert len(node.cache) == 4 and len(node.blob) == 1 << 20


def test_after_a_death_holding_the_gil_what_its_stack_may_hold_stays_whole():
    node = _dead_node()
    maybe = DeadFrames(known=[], maybe=[id(node.cache)], running=None)
    reclaim.release([node], maybe, torn=True)
    assert len(node.cache) == 4 and all(len(b) == 1 << 20 for b in node.cache)  # it and what it holds
    assert node.index == {}
    node = _dead_node()
    reclaim.release([node], DeadFrames(known=[], maybe=[id(node.cache)], running=None), torn=False)
    assert node.cache == []  # without the GIL it changed no object


def test_modules_and_classes_are_not_followed():
    node = Node()
    node.module = types.ModuleType("m")
    node.module.data = [1]
    node.cls = type("C", (), {"data": [2]})
    reclaim.release([node], NO_FRAMES, torn=False)
    assert node.module.data == [1] and node.cls.data == [2]


# -- stack_depth.py ----------------------------------------------------------


def _code_objects():
    import asyncio  # noqa: F401  (more code to check: generators, coroutines, handlers)
    import json  # noqa: F401

    seen: dict[int, types.CodeType] = {}

    def add(code):
        if id(code) not in seen:
            seen[id(code)] = code
            for const in code.co_consts:
                if isinstance(const, types.CodeType):
                    add(const)

    for module in list(sys.modules.values()):
        for obj in list(vars(module).values()):
            for f in [obj, *(vars(obj).values() if isinstance(obj, type) else ())]:
                if isinstance(getattr(f, "__code__", None), types.CodeType):
                    add(f.__code__)
    return list(seen.values())


def test_the_depth_walk_agrees_with_the_compiler_on_every_loaded_function():
    codes = _code_objects()
    assert len(codes) > 1000
    for code in codes:
        found = depths(code)
        assert max(found.values()) == code.co_stacksize, code.co_qualname  # the compiler's own maximum


def _leak(self):
    self._held.append(bytearray(self.step))


def test_below_a_calls_inputs_the_stack_is_certain():
    calls = [i for i in dis.get_instructions(_leak) if i.opname in ("PRECALL", "CALL")]
    inner, outer = calls[:2], calls[2:]
    words = [1, 2, 0, 4, 5, 66, 77]  # append, the list, NULL, bytearray, the size; then stale words
    for ins in inner:  # bytearray(self.step): the method and its list below it are done
        assert call_stack(_leak.__code__, ins.offset // 2, words) == ([1, 2], [0, 4, 5])
    for ins in outer:  # append(...): the list is an input
        assert call_stack(_leak.__code__, ins.offset // 2, [1, 2, 3, 66]) == ([], [1, 2, 3])
    load = next(i for i in dis.get_instructions(_leak) if i.opname == "LOAD_ATTR")
    assert call_stack(_leak.__code__, load.offset // 2, words) == ([], words)  # not a call: nothing certain
