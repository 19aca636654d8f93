"""jemalloc arenas per child (Debian's libjemalloc2 preloaded).

The container side runs in a subprocess started with LD_PRELOAD; it prints
what it and its children see as one JSON line.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from cloneguard.container.isolated.core import allocator, thread_arena

REPO = Path(__file__).resolve().parent.parent
JEMALLOC = Path("/usr/lib/x86_64-linux-gnu/libjemalloc.so.2")

SCRIPT = textwrap.dedent("""
    import ctypes, json, sys
    from cloneguard.container.isolated.core import CloneCore, allocator, thread_arena, thread_tcache

    def narenas():
        mallctl = ctypes.CDLL(None).mallctl
        n = ctypes.c_uint()
        size = ctypes.c_size_t(ctypes.sizeof(n))
        assert mallctl(b"arenas.narenas", ctypes.byref(n), ctypes.byref(size), None, 0) == 0
        return n.value

    out = {"allocator": allocator(), "parent_arena": thread_arena(),
           "narenas_before": narenas(), "children": []}
    with CloneCore(**json.loads(sys.argv[1])) as core:
        for i in range(4):
            seen = {}
            def child():
                junk = [bytes(100) for _ in range(1000)]   # allocate in it
                seen.update(arena=thread_arena(), tcache=thread_tcache(),
                            allocator=allocator())
            c = core.spawn(child)
            assert core.wait(c, 10).exit_code == 0
            core.release(c)
            out["children"].append(seen)
    out["narenas_after"] = narenas()
    print(json.dumps(out))
""")


def run(settings: dict, preload: bool = True) -> dict:
    env = dict(os.environ)
    env.pop("LD_PRELOAD", None)
    if preload:
        env["LD_PRELOAD"] = str(JEMALLOC)
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT, json.dumps(settings)],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


needs_jemalloc = pytest.mark.skipif(not JEMALLOC.exists(), reason="libjemalloc2 is not installed")


@needs_jemalloc
def test_each_child_gets_an_arena_of_its_own():
    out = run({})
    assert out["allocator"].startswith("jemalloc 5.")
    arenas = [c["arena"] for c in out["children"]]
    assert len(set(arenas)) == 4, arenas
    assert out["parent_arena"] not in arenas
    # created for them, beyond jemalloc's automatic arenas
    assert all(a >= out["narenas_before"] for a in arenas)
    assert out["narenas_after"] == out["narenas_before"] + 4
    assert all(c["tcache"] is True for c in out["children"])
    assert all(c["allocator"] == out["allocator"] for c in out["children"])


@needs_jemalloc
def test_auto_leaves_the_choice_to_jemalloc_and_the_tcache_can_be_off():
    out = run({"jemalloc_arena": "auto", "jemalloc_tcache": False})
    assert out["narenas_after"] == out["narenas_before"]  # none created
    assert all(c["arena"] < out["narenas_before"] for c in out["children"])
    assert all(c["tcache"] is False for c in out["children"])


def test_without_jemalloc_nothing_changes():
    out_here = (allocator(), thread_arena())
    if "jemalloc" in os.environ.get("LD_PRELOAD", ""):
        pytest.skip("this test process itself runs on jemalloc")
    assert out_here == ("glibc", None)
