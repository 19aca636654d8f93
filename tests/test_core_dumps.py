"""--core-dumps DIR (container/isolated/core_dumps.py, dumps.c): a node
process that catches a fatal signal is dumped by gdb, run by the core's
monitor, while it waits in its crash handler, into a file named after the
node, whatever lock it held; the rest goes on; a dump that cannot be written
is said why; a bad setting is refused before anything starts."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
from gil_waiters import Counter, signal_while_gil_held, spawn_busy
from std_msgs.msg import Float64, UInt64

from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness import procfs
from cloneguard.harness.system import NodeSpec, longest_gap

ROBOT = [
    NodeSpec("demo_robot", "demo_robot::Odometry", parameters={"rate": 50.0}),
    NodeSpec("demo_robot", "demo_robot::Planner", namespace="/robot"),
    # idle until asked: a signal finds it waiting, the GIL released
    NodeSpec("demo_robot", "demo_robot::MapServer", namespace="/robot"),
]
CONTAINER = os.path.join(sys.prefix, "bin", "component_container")
ET_CORE = 4
MiB = 1 << 20


def _is_core_file(path) -> bool:
    with open(path, "rb") as f:
        head = f.read(18)
    return head[:4] == b"\x7fELF" and int.from_bytes(head[16:18], "little") == ET_CORE


def test_a_crashing_node_is_dumped_under_its_name_and_the_rest_goes_on(system_factory, tmp_path):
    dumps = tmp_path / "dumps"
    robot = system_factory(ROBOT, ["--isolated", "--core-dumps", str(dumps)])
    odom = robot.topic(Float64, "/odom")
    odom.wait_count(10, timeout=10)
    pid = robot.node("/robot/map_server").pid
    at = robot.kill("/robot/map_server", signal.SIGSEGV)
    crashed = robot.wait_crashed("/robot/map_server", timeout=120)
    dump = dumps / f"core.robot.map_server.{pid}"
    assert crashed.exit_signal == signal.SIGSEGV
    assert f"core dump: {dump}" in crashed.error_message, crashed.error_message
    assert dump.is_file() and _is_core_file(dump)
    st = dump.stat()
    assert st.st_blocks * 512 < st.st_size  # its runs of zeros are holes
    _gdb_reads(dump, pid)
    odom.wait_count(len(odom) + 50, timeout=10)
    assert longest_gap(odom, at) < 0.5  # odometry never waited for the dump
    assert robot.alive()


@pytest.mark.parametrize("allocator", ["jemalloc", "glibc"])
def test_a_dump_holds_the_nodes_heap_and_not_the_untouched_reservation(system_factory, tmp_path, allocator):
    # The node mallocs 4 blocks of 1 MiB and fills them with 0x01 bytes
    # (faults::MemoryLeak, native): its heap, in its slot's range under
    # jemalloc, must be in its dump; the guard's TiBs of reserved address
    # space must not (allocguard.c cga_dump_exclude).
    dumps = tmp_path / "dumps"
    leak = NodeSpec(
        TESTRIG,
        "faults::MemoryLeak",
        name="filled",
        parameters={"kind": "native", "step": MiB, "steps": 4, "period": 0.01},
    )
    robot = system_factory([leak], ["--isolated", "--allocator", allocator, "--core-dumps", str(dumps)])
    robot.topic(UInt64, "/filled/held").wait_for(lambda m: m.data == 4 * MiB, 15, "4 MiB held")
    pid = robot.node("/filled").pid
    robot.kill("/filled", signal.SIGSEGV)
    robot.wait_crashed("/filled", timeout=120)
    dump = dumps / f"core.filled.{pid}"
    assert _is_core_file(dump)
    assert dump.stat().st_size < 64 << 30  # the container's mappings, not the reservation
    run = b"\x01" * (256 << 10)
    with open(dump, "rb") as f:
        found, tail = False, b""
        while not found and (chunk := f.read(64 << 20)):
            found, tail = run in tail + chunk, chunk[-len(run) :]
    assert found, "the node's filled blocks are not in its dump"


def _gdb_reads(dump, pid: int) -> None:
    """gdb reads the dump back: the dumped process's own tasks."""
    out = subprocess.run(
        ["gdb", "-nx", "-batch", "-ex", "info threads", sys.executable, str(dump)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert f"LWP {pid}" in out.stdout, out.stdout[-2000:] + out.stderr[-2000:]


def _slow_gdb(directory, seconds: float) -> str:
    """A PATH entry whose gdb starts ``seconds`` late: the dump's time is
    then sure to pass the watchdog's (the real dump took 5 to 12 s here)."""
    directory.mkdir()
    gdb = directory / "gdb"
    gdb.write_text(f'#!/bin/sh\nsleep {seconds}\nexec {shutil.which("gdb")} "$@"\n')
    gdb.chmod(0o755)
    return f"{directory}:{os.environ['PATH']}"


def test_a_node_that_crashes_holding_the_gil_is_dumped_and_the_rest_goes_on_after(
    system_factory, tmp_path, monkeypatch
):
    """The monitor writes the dump with no Python: a task that holds the GIL
    (inside Python's allocator) is dumped too. The node processes' Python
    waits with it meanwhile (one GIL), and goes on after. That wait is no
    hang: the watchdog (10 s) does not count it, though the dump takes longer
    here (its gdb starts 13 s late), longer than the watchdog's last resort
    (12 s) too."""
    monkeypatch.setenv("PATH", _slow_gdb(tmp_path / "bin", 13))
    dumps = tmp_path / "dumps"
    robot = system_factory(ROBOT, ["--isolated", "--core-dumps", str(dumps)])
    odom = robot.topic(Float64, "/odom")
    odom.wait_count(10, timeout=10)
    pid = robot.node("/robot/planner").pid
    # On its main task, the executor's, with the GIL held.
    at = robot.kill_at("/robot/planner", "python-allocation", sig=signal.SIGSEGV)
    assert robot.faults[-1].what == "SIGSEGV at python-allocation"
    crashed = robot.wait_crashed("/robot/planner", timeout=120)
    dump = dumps / f"core.robot.planner.{pid}"
    assert crashed.exit_signal == signal.SIGSEGV
    assert "it held the GIL" in crashed.error_message, crashed.error_message
    assert f"core dump: {dump}" in crashed.error_message, crashed.error_message
    assert _is_core_file(dump)
    _gdb_reads(dump, pid)
    odom.wait_count(len(odom) + 50, timeout=10)
    gap = longest_gap(odom, at)
    print(f"odometry's longest gap, the dump's time with the GIL held: {gap:.2f} s")
    assert gap > 13  # no Python ran while the dump was written
    assert robot.alive()


def _gdb_running_under(container_pid: int, timeout: float = 30.0) -> int:
    """The pid of the gdb the container's monitor started, once it runs."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for st in procfs.all_stats():
            if st.ppid == container_pid and st.comm == "gdb":
                return st.pid
        time.sleep(0.01)
    raise AssertionError("no gdb was started")


def test_a_node_killed_while_gdb_writes_its_dump_leaves_no_partial_file(system_factory, tmp_path):
    dumps = tmp_path / "dumps"
    robot = system_factory(ROBOT, ["--isolated", "--core-dumps", str(dumps)])
    pid = robot.node("/robot/map_server").pid
    robot.kill("/robot/map_server", signal.SIGSEGV)
    gdb = _gdb_running_under(robot.proc.pid)
    os.kill(pid, signal.SIGKILL)
    crashed = robot.wait_crashed("/robot/map_server", timeout=60)
    assert "no core dump: it died while gdb was writing its dump" in crashed.error_message, crashed.error_message
    assert procfs.wait_gone([f"/proc/{gdb}"], 60) == []
    assert list(dumps.iterdir()) == []  # what gdb had begun is removed
    robot.kill("/robot/planner", signal.SIGSEGV)  # the next crash is dumped as ever
    planner = robot.node("/robot/planner").pid
    assert f"core dump: {dumps}/core.robot.planner.{planner}" in robot.wait_crashed("/robot/planner").error_message


def test_a_file_in_the_way_is_neither_written_over_nor_taken_for_the_dump(system_factory, tmp_path):
    """Found by a newcomer: a directory where the dump was to go was
    reported as the dump ("core dump written: 0 MiB")."""
    dumps = tmp_path / "dumps"
    robot = system_factory(ROBOT, ["--isolated", "--core-dumps", str(dumps)])
    pid = robot.node("/robot/map_server").pid
    in_the_way = dumps / f"core.robot.map_server.{pid}"
    in_the_way.mkdir()
    robot.kill("/robot/map_server", signal.SIGSEGV)
    crashed = robot.wait_crashed("/robot/map_server", timeout=60)
    assert f"no core dump: something is in the way: {in_the_way}" in crashed.error_message, crashed.error_message
    assert in_the_way.is_dir() and list(in_the_way.iterdir()) == []


def test_two_nodes_crashing_at_once_are_dumped_one_after_the_other(system_factory, tmp_path):
    """The monitor writes one dump at a time; the second crash waits its turn."""
    dumps = tmp_path / "dumps"
    robot = system_factory(ROBOT, ["--isolated", "--core-dumps", str(dumps)])
    pids = {name: robot.node(name).pid for name in ("/robot/planner", "/robot/map_server")}
    for name in pids:
        robot.kill(name, signal.SIGSEGV)
    for name, pid in pids.items():
        dump = dumps / f"core{name.replace('/', '.')}.{pid}"
        assert f"core dump: {dump}" in robot.wait_crashed(name, timeout=120).error_message
        assert _is_core_file(dump)
    assert robot.alive()


def test_a_node_holding_the_gil_that_waits_behind_another_dump_is_no_hang_either(system_factory, tmp_path, monkeypatch):
    """Found by CI: two nodes crashed at once, the one holding the GIL was
    dumped second, and the watchdog ended the container. Here the planner
    crashes holding the GIL while the map server's dump is under way, and
    holds it through both dumps (each gdb starts 7 s late: over 12 s in all,
    the watchdog's last resort)."""
    monkeypatch.setenv("PATH", _slow_gdb(tmp_path / "bin", 7))
    dumps = tmp_path / "dumps"
    robot = system_factory(ROBOT, ["--isolated", "--core-dumps", str(dumps)])
    odom = robot.topic(Float64, "/odom")
    odom.wait_count(10, timeout=10)
    map_server, planner = robot.node("/robot/map_server").pid, robot.node("/robot/planner").pid
    robot.kill("/robot/map_server", signal.SIGSEGV)
    _gdb_running_under(robot.proc.pid)  # its dump is under way
    at = robot.kill_at("/robot/planner", "python-allocation", sig=signal.SIGSEGV)  # GIL held
    for name, pid in (("/robot/map_server", map_server), ("/robot/planner", planner)):
        crashed = robot.wait_crashed(name, timeout=120)
        assert f"core dump: {dumps}/core{name.replace('/', '.')}.{pid}" in crashed.error_message, crashed.error_message
    assert "it held the GIL" in crashed.error_message, crashed.error_message
    odom.wait_count(len(odom) + 50, timeout=10)
    gap = longest_gap(odom, at)
    print(f"odometry's longest gap, both dumps' time with the GIL held: {gap:.2f} s")
    assert gap > 12  # past the last resort's time, on CLOCK_MONOTONIC
    assert robot.alive()


def test_a_dump_that_cannot_be_written_is_said_why(system_factory, tmp_path):
    dumps = tmp_path / "dumps"
    robot = system_factory(ROBOT, ["--isolated", "--core-dumps", str(dumps)])
    odom = robot.topic(Float64, "/odom")
    dumps.rmdir()  # gdb cannot create the file now
    robot.kill("/robot/map_server", signal.SIGSEGV)
    crashed = robot.wait_crashed("/robot/map_server", timeout=60)
    assert crashed.exit_signal == signal.SIGSEGV
    assert f"no core dump: gdb wrote none: Failed to open '{dumps}/core." in crashed.error_message, (
        crashed.error_message
    )
    odom.wait_count(len(odom) + 20, timeout=10)
    assert robot.alive()


def test_a_kill_leaves_no_dump(system_factory, tmp_path):
    dumps = tmp_path / "dumps"
    robot = system_factory(ROBOT, ["--isolated", "--core-dumps", str(dumps)])
    robot.kill("/robot/planner", signal.SIGKILL)
    assert "core dump" not in robot.wait_crashed("/robot/planner").error_message
    assert list(dumps.iterdir()) == []


@pytest.mark.parametrize(
    "args, env, says",
    [
        (["--core-dumps", "{tmp}"], {}, "--core-dumps needs --isolated"),
        (["--isolated", "--core-dumps", "{tmp}", "--no-crash-report"], {}, "--core-dumps needs the crash report"),
        (["--isolated", "--core-dumps", "{tmp}"], {"PATH": "/nonexistent"}, "it needs gdb"),
        (["--isolated", "--core-dumps", "{file}"], {}, "is not a directory"),
    ],
    ids=["thread-mode", "no-crash-report", "no-gdb", "a-file"],
)
def test_core_dumps_that_cannot_be_written_are_refused_at_start_up(tmp_path, args, env, says):
    (tmp_path / "a-file").write_text("")
    argv = [a.format(tmp=tmp_path / "dumps", file=tmp_path / "a-file") for a in args]
    proc = subprocess.run([CONTAINER, *argv], env={**os.environ, **env}, capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and says in proc.stderr, proc.stderr[-2000:]
    assert not (tmp_path / "dumps").exists() or says != "it needs gdb"


def test_a_node_crashing_while_it_waits_for_the_gil_holds_nobody_up_during_its_dump(tmp_path):
    """Found by CI (1 run in ~10 under load): a node SIGSEGV'd while it
    waited for the GIL kept its place in the GIL's condvar while it waited
    for its dump, so the next thread to hand the GIL on waited for it too,
    holding the GIL's mutex: all of the container's Python stood still for
    the dump, and two dumps in a row outlasted the watchdog. Here the dump
    is held back (gdb starts only when `released` appears, 5 s on); this
    thread and a counting one must get the GIL back long before that. (With
    no other thread wanting the GIL, this one would wait anyway, in
    drop_gil, to hand it to the waiter that asked for it: the container
    always has others.)"""
    from cloneguard.container.isolated import core_dumps
    from cloneguard.container.isolated.core import CloneCore, Repair

    if (why := core_dumps.unavailable(tmp_path)) is not None:
        pytest.skip(why)
    real = core_dumps.tools()
    gate, released = tmp_path / "gate", tmp_path / "released"
    os.mkfifo(gate)
    gdb = tmp_path / "gdb"
    gdb.write_text(f'#!/bin/sh\nread go < "{gate}"\nexec "{real.gdb}" "$@"\n')
    gdb.chmod(0o755)
    dump = tmp_path / "core.waiter"
    core = CloneCore(dump_tools=core_dumps.Tools(str(gdb), real.fallocate))
    counter = Counter()
    helpers: list[subprocess.Popen] = []
    try:
        c = spawn_busy(core)
        core.name_dump(c, str(dump))
        opener = subprocess.Popen(["sh", "-c", f'sleep 5; : > "{released}"; echo go 1<>"{gate}"'])
        helpers.append(opener)
        signal_while_gil_held(c.pid, "SEGV")
        assert counter.advances(timeout=1.0) and not released.exists(), (
            "Python ran again only once the dump was let through"
        )
        assert opener.wait(30) == 0
        death = core.wait(c, 120)
        assert death is not None and death.exit_signal == signal.SIGSEGV
        assert death.core_file == str(dump) and _is_core_file(dump), death.core_missing
        assert Repair.COND_WAITER in death.repairs, death.repairs
        core.release(c)
        # The condvar still works for many hand-overs.
        sib = core.spawn(lambda: [sum(range(100)) for _ in range(20000)])
        death = core.wait(sib, 20)
        assert death is not None and death.exit_code == 0
        core.release(sib)
    finally:
        counter.stop()
        core.close()  # ends a gdb still waiting at the gate
        for helper in helpers:
            helper.wait(30)
