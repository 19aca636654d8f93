"""Long life: hundreds of loads do not drain a container (bench/leaks.py).

A cycle loads and unloads a node and fails one construction. After a
warm-up (a burst of concurrent requests, so the container's bounded thread
pools are full, then plain cycles), RSS may grow by at most
LIMIT_MIB_PER_CYCLE a cycle, and fds and threads not at all; no node
process is left at rest.

Thread mode and the shared profile build nodes on the container's own
rclpy Context, and there rclpy 7.1 / rmw_fastrtps (the Jazzy wheels) leaks:
creating and destroying a node while another node lives in the same
Context loses ~0.1 MiB of malloc'd memory and takes longer each time
(measured in a plain rclpy loop, no container involved: 0.0014 MiB per
cycle with no other node, 0.10 MiB with one; 300 cycles took 3 s at first
and 34 s after 1,500). Their RSS bound is an expected failure, strict: it
shows the day that leak is gone. The per-node profile gives every node a
Context of its own, which goes with its process, and stays flat.
"""
import pytest

from bench import leaks

UPSTREAM_LEAK = pytest.mark.xfail(
    strict=True, reason="rclpy/rmw_fastrtps (Jazzy wheels) leak ~0.1 MiB per node created and "
                        "destroyed beside another node in one Context (module docstring)")


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mode", ["per-node", "cgroups", "threads", "shared"])
def test_load_cycles_leave_fds_threads_and_processes_flat(mode, tmp_path):
    g = leaks.measure(mode, cycles=60, warmup=20, log_dir=tmp_path)
    assert g.fds <= 0 and g.threads <= 0, (g.before, g.after)
    assert g.after.node_processes == 0


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mode", [
    "per-node", "cgroups",
    pytest.param("threads", marks=UPSTREAM_LEAK), pytest.param("shared", marks=UPSTREAM_LEAK)])
def test_load_cycles_leave_rss_flat(mode, tmp_path):
    g = leaks.measure(mode, cycles=100, warmup=20, log_dir=tmp_path)
    assert g.rss_mib_per_cycle <= leaks.LIMIT_MIB_PER_CYCLE, (
        f"{mode}: {g.rss_mib_per_cycle:+.4f} MiB per cycle ({g.before.rss_kib} -> {g.after.rss_kib} KiB)")
