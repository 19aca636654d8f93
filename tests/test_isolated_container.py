"""--isolated: each node in its own clone(CLONE_VM) process, on real containers."""

import os
import resource
import signal
import time

import pytest
from cloneguard_interfaces.msg import ComponentEvent
from cloneguard_interfaces.srv import Echo
from std_msgs.msg import String, UInt64

from cloneguard.container import allocator
from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness import procfs

PKG = "cloneguard"
PROFILES = [
    pytest.param(["--isolated", "--profile", "per-node"], id="per-node"),
    pytest.param(["--isolated", "--profile", "shared"], id="shared"),
]


def _loaded_pid(client, unique_id):
    return client.wait_for_event(ComponentEvent.LOADED, unique_id=unique_id).pid


@pytest.mark.parametrize("container_args", PROFILES)
def test_each_node_is_its_own_process_in_one_address_space(client, container):
    ids = [client.load_ok(PKG, "cloneguard::Heartbeat", node_name=f"hb{i}").unique_id for i in range(3)]
    pids = [_loaded_pid(client, uid) for uid in ids]
    assert len(set(pids)) == 3 and container.pid not in pids
    for pid in pids:
        stat = procfs.stat(pid)
        assert stat is not None and (stat.ppid, stat.pgrp) == (container.pid, container.pgid)
        assert procfs.same_address_space(container.pid, pid)
    # A plain process is not in that address space (the check can say no).
    assert not procfs.same_address_space(container.pid, os.getpid())
    # ps and top show each by its node's name (the kernel keeps 15 bytes).
    for i, pid in enumerate(pids):
        _wait_for_comm(pid, f"hb{i}")


@pytest.mark.parametrize("container_args", [["--isolated"]])
def test_a_node_process_is_named_after_its_node_cut_to_the_kernels_15_bytes(client):
    uid = client.load_ok(
        PKG, "cloneguard::Heartbeat", node_name="a_rather_long_node_name", node_namespace="/ns"
    ).unique_id
    _wait_for_comm(_loaded_pid(client, uid), "a_rather_long_n")


def _wait_for_comm(pid: int, name: str, timeout: float = 10.0) -> None:
    """Its node starts spinning just after LOADED: the name comes then."""
    deadline = time.monotonic() + timeout
    while (comm := _comm(pid)) != name:
        assert time.monotonic() < deadline, f"pid {pid} is named {comm!r}, not {name!r}"
        time.sleep(0.02)


@pytest.mark.parametrize("container_args", PROFILES)
def test_messages_flow_between_children_and_to_an_outside_node(client):
    chatter = client.subscribe(String, "/chatter")
    counts = client.subscribe(UInt64, "/listener/received")
    client.load_ok(PKG, "cloneguard::Talker", parameters={"period": 0.02})
    client.load_ok(PKG, "cloneguard::Listener")
    chatter.wait_count(5, timeout=10)
    counts.wait_for(lambda m: m.data >= 5, timeout=10, what="listener count >= 5")


@pytest.mark.parametrize("container_args", PROFILES)
def test_a_service_is_served_by_the_nodes_own_process(client):
    uid = client.load_ok(PKG, "cloneguard::EchoService").unique_id
    pid = _loaded_pid(client, uid)
    req = Echo.Request(data="ping")
    answer = client.call(client.service_client(Echo, "/echo/echo"), req)
    assert (answer.data, answer.served, answer.pid) == ("ping", 1, pid)


@pytest.mark.parametrize("container_args", PROFILES)
@pytest.mark.parametrize("sig", [signal.SIGSEGV, signal.SIGABRT, signal.SIGKILL], ids=lambda s: s.name)
def test_one_child_dies_and_the_rest_goes_on(client, container, sig):
    victim = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="victim")
    survivor = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="survivor")
    victim_pid = _loaded_pid(client, victim.unique_id)
    beats = client.subscribe(UInt64, "/survivor/heartbeat")
    beats.wait_count(3, timeout=10)

    os.kill(victim_pid, sig)
    crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=victim.unique_id)
    assert (crashed.pid, crashed.exit_signal, crashed.exit_code) == (victim_pid, sig, 0)
    assert crashed.full_node_name == "/victim"
    assert signal.Signals(sig).name in crashed.error_message

    # The container still answers, the survivor still beats, new loads work.
    assert container.alive()
    assert client.list() == [(survivor.unique_id, "/survivor")]
    seen = len(beats)
    beats.wait_count(seen + 5, timeout=10)
    again = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="victim")
    client.subscribe(UInt64, "/victim/heartbeat").wait_count(3, timeout=10)
    assert client.list() == [(survivor.unique_id, "/survivor"), (again.unique_id, "/victim")]


@pytest.mark.parametrize("container_args", PROFILES)
def test_unload_stops_and_reaps_the_child(client, container):
    uid = client.load_ok(PKG, "cloneguard::Talker").unique_id
    pid = _loaded_pid(client, uid)
    assert client.unload(uid).success
    unloaded = client.wait_for_event(ComponentEvent.UNLOADED, unique_id=uid)
    assert unloaded.pid == pid
    assert procfs.stat(pid) is None, "the child was not reaped"
    assert procfs.zombies_of(container.pid) == []


@pytest.mark.parametrize("container_args", PROFILES)
def test_shutdown_with_twenty_nodes_stops_and_reaps_every_child(client, container):
    for i in range(20):
        client.load_ok(PKG, "cloneguard::Heartbeat", node_name=f"hb{i}")
    assert len(procfs.children_of(container.pid)) >= 20
    container.signal(signal.SIGTERM)
    assert container.wait(timeout=10) == 0, container.log_text()[-3000:]
    assert container.group_members() == []


def test_isolated_load_failures_answer_like_thread_mode(container_factory, misfit_env):
    proc = container_factory.start(["--isolated"], extra_env=misfit_env)
    client = container_factory.connect(proc)
    resp = client.load("misfit-components", "misfits::Raises")
    assert not resp.success and "sensor not found" in resp.error_message
    assert client.load(PKG, "cloneguard::Nope").error_message == (
        "Failed to find class with the requested plugin name."
    )
    assert client.load_ok(PKG, "cloneguard::Talker").unique_id == 2
    assert client.list() == [(2, "/talker")]


@pytest.mark.parametrize("container_args", PROFILES)
def test_a_child_dying_with_a_container_lock_leaves_it_recoverable(client, container):
    survivor = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="survivor")
    beats = client.subscribe(UInt64, "/survivor/heartbeat")
    beats.wait_count(3, timeout=10)
    holder = client.load_ok(TESTRIG, "faults::DieHoldingContainerLock", parameters={"delay": 0.3})
    crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=holder.unique_id)
    assert crashed.exit_signal == signal.SIGKILL
    # The next locker got EOWNERDEAD and repaired the half-written slot,
    # which the container announces once ...
    repair = client.wait_for_event(ComponentEvent.REPAIRED, unique_id=holder.unique_id)
    assert repair.repaired_state == "progress-board"
    assert "half-written" in repair.error_message
    # ... and everyone goes on: the survivor beats (it takes that lock after
    # every callback), the container answers and loads.
    seen = len(beats)
    beats.wait_count(seen + 5, timeout=10)
    again = client.load_ok(PKG, "cloneguard::Talker")
    assert client.list() == [(survivor.unique_id, "/survivor"), (again.unique_id, "/talker")]
    assert sum(1 for e in client.events.messages() if e.event_type == ComponentEvent.REPAIRED) == 1


@pytest.mark.parametrize("container_args", [["--isolated", "--restart-policy", "on-crash"]])
def test_restart_policy_reloads_a_crashed_node_with_backoff(client):
    first = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="phoenix")
    pid = _loaded_pid(client, first.unique_id)
    os.kill(pid, signal.SIGKILL)
    client.wait_for_event(ComponentEvent.CRASHED, unique_id=first.unique_id)
    again = client.events.wait_for(
        lambda e: (
            e.event_type == ComponentEvent.LOADED and e.full_node_name == "/phoenix" and e.unique_id != first.unique_id
        ),
        timeout=10,
        what="LOADED of the restarted node",
    )
    assert again.unique_id > first.unique_id and again.pid != pid
    assert client.list() == [(again.unique_id, "/phoenix")]
    client.subscribe(UInt64, "/phoenix/heartbeat").wait_count(3, timeout=10)
    # Killed again at once: the second delay doubles (0.5 s -> 1 s).
    os.kill(again.pid, signal.SIGKILL)
    crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=again.unique_id)
    third = client.events.wait_for(
        lambda e: e.event_type == ComponentEvent.LOADED and e.unique_id > again.unique_id,
        timeout=10,
        what="second restart",
    )
    gap_s = ((third.stamp.sec - crashed.stamp.sec) * 1e9 + third.stamp.nanosec - crashed.stamp.nanosec) / 1e9
    assert 0.9 <= gap_s < 5, gap_s


@pytest.mark.parametrize("container_args", [["--isolated", "--restart-policy", "on-crash", "--restart-limit", "2"]])
def test_a_node_that_dies_at_every_start_is_restarted_up_to_the_limit(client, container):
    client.load_ok(TESTRIG, "faults::SegfaultInCallback", node_name="loop", parameters={"delay": 0.01})
    seen = []

    def third_crash(e):
        if e.event_type != ComponentEvent.CRASHED:
            return False
        seen.append(e)
        return len(seen) == 3

    client.events.wait_for(
        third_crash,
        timeout=15,
        what="the third crash",
    )
    assert [m.error_message.rsplit("; ", 1)[1] for m in seen] == [
        "restarting in 0.5 s (restart 1, 1 of 2 in a row)",
        "restarting in 1 s (restart 2, 2 of 2 in a row)",
        "not restarted again: it died 3 times in a row, each within 60 s of its start (restart limit 2)",
    ]
    assert all(m.error_message.startswith("killed by SIGSEGV") for m in seen)
    # The next restart would have come 2 s later: none comes, and it is gone.
    time.sleep(3)
    loaded = [m for m in client.events.messages() if m.event_type == ComponentEvent.LOADED]
    assert len(loaded) == 3 and client.list() == []
    assert "not restarted again" in container.log_text()


def test_restart_policy_needs_isolated_mode(container_factory):
    proc = container_factory.start(["--restart-policy", "on-crash"])
    assert proc.wait(timeout=20) != 0
    assert "--restart-policy needs --isolated" in proc.log_text()


@pytest.mark.parametrize("intra", [False, True], ids=["dds", "intra-process"])
@pytest.mark.parametrize("container_args", PROFILES)
def test_an_idle_node_stops_gracefully_without_sigkill(client, container, intra):
    # A listener with nothing to listen to has no callback to wake it: the
    # stop has to wake its executor by itself.
    uid = client.load_ok(
        PKG,
        "cloneguard::Listener",
        remap_rules=["chatter:=nobody_talks_here"],
        extra_arguments={"use_intra_process_comms": intra},
    ).unique_id
    assert client.unload(uid).success
    client.wait_for_event(ComponentEvent.UNLOADED, unique_id=uid)
    assert "did not stop within" not in container.log_text()
    assert "left in memory" not in container.log_text()


@pytest.mark.parametrize("container_args", PROFILES)
def test_an_outside_sigterm_stops_a_node_cleanly(client, container):
    uid = client.load_ok(PKG, "cloneguard::Heartbeat").unique_id
    marker = client.load_ok(PKG, "cloneguard::Heartbeat", node_name="marker").unique_id
    pid = _loaded_pid(client, uid)
    os.kill(pid, signal.SIGTERM)
    ev = client.wait_for_event(ComponentEvent.CRASHED, unique_id=uid)
    assert (ev.exit_signal, ev.exit_code) == (0, 0)
    assert "after an outside SIGTERM" in ev.error_message
    # The CRASHED can come before the container has released the process:
    # the next death, dealt with after it on the same thread, marks its end.
    os.kill(_loaded_pid(client, marker), signal.SIGKILL)
    container.wait_for_log(rf"unique_id {marker}: the dead process", timeout=10)
    assert f"unique_id {uid}: the dead process" not in container.log_text()  # released, not leaked
    assert client.list() == []


@pytest.mark.parametrize(
    "container_args, per_task, guard",
    [
        (["--isolated", "--allocator", "glibc"], True, True),
        (["--isolated", "--allocator", "glibc", "--no-alloc-guard"], True, False),
        (["--isolated", "--allocator", "glibc", "--shared-arenas", "--no-alloc-guard"], False, False),
        ([], False, False),
    ],
)
def test_isolated_mode_gives_each_task_a_glibc_arena(client, container, per_task, guard):
    # The ready line names the allocator; mallopt's effect is glibc's own.
    # It is logged once the service threads run, so a request can be
    # answered before it is written: wait for it.
    line = container.wait_for_log(r".* ready \(.*", timeout=10).group(0)
    assert ("glibc malloc, an arena per task" in line) == per_task, line
    assert ("allocator guard" in line) == guard, line


def test_an_isolated_container_runs_on_jemalloc_by_default(container_factory):
    # Installed by scripts/setup.sh: where it is not, the next test's rule applies.
    assert allocator.jemalloc_path() is not None
    proc = container_factory.start(["--isolated"])
    container_factory.connect(proc)
    line = proc.wait_for_log(r".* ready \(.*", timeout=10).group(0)
    assert "jemalloc 5." in line and "allocator guard" in line, line


def test_without_libjemalloc2_an_isolated_container_chooses_glibc_and_says_why(monkeypatch):
    from cloneguard.container import cli

    monkeypatch.setattr(allocator, "jemalloc_path", lambda: None)
    opts = cli.parse_args(["--isolated"])
    assert (opts.allocator, opts.jemalloc) == ("glibc", False)
    assert opts.allocator_why.startswith(allocator.JEMALLOC_MISSING)
    for asked in (["--isolated", "--allocator", "glibc"], []):  # chosen, or thread mode's default: no warning
        opts = cli.parse_args(asked)
        assert (opts.allocator, opts.allocator_why) == ("glibc", None)
    monkeypatch.undo()
    assert cli.parse_args(["--isolated"]).allocator == "jemalloc"
    assert cli.parse_args(["--isolated", "--jemalloc"]).allocator == "jemalloc"


def test_a_handoff_waits_on_descriptors_past_select_limit():
    """Crashed per-node nodes leave their sockets open in the shared fd
    table: after ~110 crashes a new pipe's fds are past 1024, where select()
    refuses (found by a deep run: every load after that failed)."""
    from cloneguard.container.isolated.host import _Handoff

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if max(soft, hard) < 1200:
        pytest.skip(f"an open-file limit of {max(soft, hard)} cannot reach past 1024")
    resource.setrlimit(resource.RLIMIT_NOFILE, (max(soft, 1200), hard))
    filler = [os.open("/dev/null", os.O_RDONLY) for _ in range(1100)]
    try:
        handoff = _Handoff()
        assert handoff._r >= 1024
        assert handoff.wait(0.01) is None
        handoff.post(b"R")
        assert handoff.wait(1.0) == b"R"
        handoff.close()
    finally:
        for fd in filler:
            os.close(fd)
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def _open_file_limits(pid: int) -> tuple[int, int]:
    with open(f"/proc/{pid}/limits") as f:
        line = next(x for x in f if x.startswith("Max open files"))
    soft, hard = line.split()[3:5]
    return int(soft), int(hard)


@pytest.mark.parametrize("args, raised", [(["--isolated"], True), ([], False)], ids=["isolated", "threads"])
def test_isolated_mode_raises_its_open_file_limit_to_the_hard_one(container_factory, args, raised):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard <= 1024:
        pytest.skip(f"the hard open-file limit is {hard}: nothing to raise to")
    resource.setrlimit(resource.RLIMIT_NOFILE, (1024, hard))  # the container inherits it
    try:
        proc = container_factory.start(args)
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    container_factory.connect(proc).list()
    limits = _open_file_limits(proc.pid)
    if raised:
        assert limits[0] == limits[1] and limits[0] > 1024, limits
        assert f"open-file limit raised from 1024 to {limits[0]}" in proc.log_text()
    else:
        assert limits[0] == 1024


@pytest.mark.parametrize("container_args", PROFILES)
def test_each_crash_report_shows_its_own_process_python_stack(client, container):
    """A node process's context (its TLS block and allocator slot) is
    reused by the next one; a crashed one's thread state is never deleted.
    The next node in that block was once bound to the dead one's thread
    state, and its report showed the aborted node's callback."""
    aborted = client.load_ok(TESTRIG, "faults::AbortInCallback", parameters={"delay": 0.1})
    client.wait_for_event(ComponentEvent.CRASHED, unique_id=aborted.unique_id)
    for i in range(3):  # later nodes, some in the aborted one's context
        victim = client.load_ok(PKG, "cloneguard::Heartbeat", node_name=f"victim{i}")
        pid = _loaded_pid(client, victim.unique_id)
        client.subscribe(UInt64, f"/victim{i}/heartbeat").wait_count(2, timeout=10)
        os.kill(pid, signal.SIGSEGV)
        client.wait_for_event(ComponentEvent.CRASHED, unique_id=victim.unique_id)
        head = f"cloneguard: pid {pid} Python stack (most recent call first):\n"
        deadline = time.monotonic() + 10
        while f"cloneguard: pid {pid} native stack:" not in container.log_text():
            assert time.monotonic() < deadline, f"no crash report for pid {pid}"
            time.sleep(0.05)
        log = container.log_text()
        stack = log[log.index(head) : log.index(f"cloneguard: pid {pid} native stack:")]
        assert " in fire" not in stack and "components.py" not in stack, stack
        # Its own loop: mostly idle in its executor's wait, but the signal
        # may land in the loop's own steps around a callback (seen once in
        # ~20 runs: board.beat, right after a heartbeat).
        assert "_spin_until_stopped" in stack, stack


def _comm(pid: int) -> str | None:
    stat = procfs.stat(pid)
    return None if stat is None else stat.comm
