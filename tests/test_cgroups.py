"""--cgroups: each isolated node born in its own cgroup, with an optional CPU quota."""

import os
import signal
import subprocess
import time
from pathlib import Path

import pytest
from cloneguard_interfaces.msg import ComponentEvent

from cloneguard.container.isolated.cgroups import cgroup2_mount, v1_cpu_mount
from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness import procfs

PKG = "cloneguard"
CG_ARGS = ["--isolated", "--cgroups"]

V2 = cgroup2_mount()
HAS_CPU = v1_cpu_mount() is not None or (V2 is not None and "cpu" in (V2 / "cgroup.controllers").read_text())


def _v2() -> Path:
    assert V2 is not None, "the container made its cgroups where there is no cgroup2 mount"
    return V2


needs_cpu = pytest.mark.skipif(not HAS_CPU, reason="no cpu controller on this machine")


def _cgroup_dirs(container_pid):
    name = f"cloneguard-{container_pid}"
    dirs = [_v2() / name]
    if (v1_cpu := v1_cpu_mount()) is not None:
        dirs.append(v1_cpu / name)
    return dirs


@pytest.mark.parametrize("container_args", [CG_ARGS])
def test_each_node_is_born_in_its_own_cgroup_which_goes_with_it(client, container):
    uid = client.load_ok(PKG, "cloneguard::Heartbeat").unique_id
    pid = client.wait_for_event(ComponentEvent.LOADED, unique_id=uid).pid
    v2_line = [ln for ln in Path(f"/proc/{pid}/cgroup").read_text().splitlines() if ln.startswith("0::")][0]
    assert v2_line == f"0::/cloneguard-{container.pid}/node-{uid}"
    assert (_v2() / f"cloneguard-{container.pid}" / f"node-{uid}").is_dir()
    client.unload(uid)
    assert not (_v2() / f"cloneguard-{container.pid}" / f"node-{uid}").exists()


@needs_cpu
@pytest.mark.parametrize("container_args", [CG_ARGS])
def test_a_cpu_quota_throttles_a_busy_node(client, container):
    resp = client.load_ok(
        TESTRIG,
        "faults::HangInCallback",
        parameters={"mode": "spin", "delay": 0.0},
        extra_arguments={"cloneguard.cpu_quota": 0.2},
    )
    pid = client.wait_for_event(ComponentEvent.LOADED, unique_id=resp.unique_id).pid
    v1 = v1_cpu_mount()
    group = (v1 if v1 else _v2()) / f"cloneguard-{container.pid}" / f"node-{resp.unique_id}"
    assert str(pid) in (group / "cgroup.procs").read_text().split()
    # A node spinning at 100% against a 20% quota gets throttled, in the
    # kernel's own count, within a few periods.
    deadline = time.monotonic() + 5
    while True:
        stat = dict(line.split() for line in (group / "cpu.stat").read_text().splitlines())
        if int(stat["nr_throttled"]) > 0:
            break
        assert time.monotonic() < deadline, f"never throttled: {stat}"
        time.sleep(0.1)


@needs_cpu
@pytest.mark.parametrize("container_args", [CG_ARGS])
def test_a_throttled_node_is_unthrottled_to_stop_cleanly(client, container):
    # At 0.01 CPUs a clean stop would take seconds; killed instead, the node
    # would leave its participant behind (and in the graph).
    for plugin in ("cloneguard::EchoService", "cloneguard::Talker"):
        uid = client.load_ok(PKG, plugin, extra_arguments={"cloneguard.cpu_quota": 0.01}).unique_id
        client.wait_for_event(ComponentEvent.LOADED, unique_id=uid)
        assert client.unload(uid).success
    log = container.log_text()
    assert "did not stop" not in log and "left in memory" not in log, log


@pytest.mark.parametrize("container_args", [[], ["--isolated"]])
def test_a_cpu_quota_without_cgroups_is_refused(client):
    resp = client.load(PKG, "cloneguard::Talker", extra_arguments={"cloneguard.cpu_quota": 0.5})
    assert not resp.success and "needs" in resp.error_message and "--cgroups" in resp.error_message


@pytest.mark.parametrize("container_args", [CG_ARGS])
def test_stopping_the_container_removes_its_cgroups(client, container):
    client.load_ok(PKG, "cloneguard::Talker", extra_arguments={"cloneguard.cpu_quota": 0.5})
    client.load_ok(PKG, "cloneguard::Heartbeat")
    dirs = _cgroup_dirs(container.pid)
    assert all(d.is_dir() for d in dirs)
    container.stop()
    assert container.exit_status.returncode == 0
    assert not any(d.exists() for d in dirs)


@pytest.mark.parametrize("container_args", [CG_ARGS])
def test_a_killed_container_s_cgroups_are_removed_by_its_janitor(client, container):
    # SIGKILL (or the watchdog's exit) gives the container no shutdown: its
    # janitor, a process of its own, empties and removes the cgroups once
    # the container and its node processes are gone.
    # With a quota: in the v1 cpu hierarchy too, on a machine where it is there.
    quota = {"cloneguard.cpu_quota": 0.5} if HAS_CPU else {}
    client.load_ok(PKG, "cloneguard::Talker", extra_arguments=quota)
    client.load_ok(PKG, "cloneguard::Heartbeat")
    dirs = _cgroup_dirs(container.pid)
    assert all(d.is_dir() for d in dirs)
    container.signal(signal.SIGKILL)
    assert container.wait(timeout=10) == -signal.SIGKILL
    left = procfs.wait_gone(dirs, 10)
    assert left == [], f"still there 10 s after the kill: {left}"
    # (A cgroup with a live task in it cannot be removed: its node
    # processes were gone, or killed by the janitor, first.)
    log = container.log_text()
    assert f"cloneguard cgroup janitor: the container (pid {container.pid}) ended without removing" in log
    assert "could not remove" not in log


def _janitors_of(root: Path) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except (OSError, ValueError):
            continue
        if any(a.endswith(b"cgroup_janitor.py") for a in argv) and str(root).encode() in argv:
            found.append(int(entry.name))
    return found


def test_a_closed_node_cgroups_janitor_ends_and_is_no_child_of_ours(request):
    from cloneguard.container.isolated.cgroups import NodeCgroups

    cgroups = NodeCgroups(f"cloneguard-test-janitor-{os.getpid()}")
    request.addfinalizer(cgroups.close)
    [janitor] = _janitors_of(cgroups.v2_root)  # waiting for us
    assert janitor not in procfs.children_of(os.getpid())
    cgroups.remove(cgroups.create(3))
    assert cgroups.close() == []
    assert not cgroups.v2_root.exists()
    deadline = time.monotonic() + 10
    while _janitors_of(cgroups.v2_root):
        assert time.monotonic() < deadline, "the janitor did not end once the pipe closed"
        time.sleep(0.05)


def _stale_tree(name: str) -> list[Path]:
    """What a SIGKILLed container leaves: its root and a node's cgroup in
    each hierarchy it used, with no process in them."""
    v1_cpu = v1_cpu_mount()
    roots = [_v2() / name] + ([v1_cpu / name] if v1_cpu is not None else [])
    for root in roots:
        (root / "node-7").mkdir(parents=True)
    return roots


def test_an_empty_cgroup_left_under_our_name_is_reclaimed(request):
    from cloneguard.container.isolated.cgroups import NodeCgroups

    name = f"cloneguard-test-stale-{os.getpid()}"
    roots = _stale_tree(name)
    cgroups = NodeCgroups(name)
    request.addfinalizer(cgroups.close)
    assert cgroups.reclaimed == [str(r) for r in roots]
    assert not (roots[0] / "node-7").exists()
    cg = cgroups.create(7)  # the name a stale node held is free again
    cgroups.remove(cg)
    assert cgroups.close() == []
    assert not any(r.exists() for r in roots)


def test_a_cgroup_under_our_name_with_a_live_process_is_refused_not_touched():
    from cloneguard.container.isolated.cgroups import CgroupsUnavailable, NodeCgroups

    name = f"cloneguard-test-busy-{os.getpid()}"
    roots = _stale_tree(name)
    sleeper = subprocess.Popen(["sleep", "60"])
    try:
        (roots[0] / "node-7" / "cgroup.procs").write_text(str(sleeper.pid))
        with pytest.raises(CgroupsUnavailable, match="has processes in"):
            NodeCgroups(name)
        assert (roots[0] / "node-7").is_dir()
        assert f"/{name}/node-7" in Path(f"/proc/{sleeper.pid}/cgroup").read_text()
    finally:
        sleeper.kill()
        sleeper.wait()
        from cloneguard.container.isolated.cgroups import _rmdir

        for root in roots:
            for d in sorted((d for d in root.rglob("*") if d.is_dir()), reverse=True) + [root]:
                _rmdir(d)
