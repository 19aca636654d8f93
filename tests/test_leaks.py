"""Long life: hundreds of loads do not drain a container (bench/leaks.py).

A cycle loads and unloads a node and fails two constructions (a bad
``period``, refused by the component; a ``use_sim_time`` string, refused by
rclpy's ``Node.__init__`` part-way). After a
warm-up (a burst of concurrent requests, so the container's bounded thread
pools are full, then plain cycles), RSS may grow by at most
LIMIT_MIB_PER_CYCLE a cycle, and fds and threads not at all; no child
process is left at rest but the per-node profile's warm spare.

Thread mode and the shared profile build nodes on the container's own
rclpy Context, where rclpy 7.1 never finalizes a node's type description
service (~0.1 MiB and two DDS endpoints per node, measured); the container
finalizes it itself (container/construction.py). The per-node profile gives
every node a Context of its own, which goes with its process.
"""

import pytest

from cloneguard.bench import leaks


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mode", ["per-node", "cgroups", "threads", "shared"])
def test_load_cycles_leave_fds_threads_and_processes_flat(mode, tmp_path):
    g = leaks.measure(mode, cycles=60, warmup=20, log_dir=tmp_path)
    assert g.fds <= 0 and g.threads <= 0, (g.before, g.after, g.new_fds())
    assert g.after.child_processes == leaks.PROCESSES_AT_REST.get(mode, 0)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("mode", ["per-node", "cgroups", "threads", "shared"])
def test_load_cycles_leave_rss_flat(mode, tmp_path):
    g = leaks.measure(mode, cycles=100, warmup=20, log_dir=tmp_path)
    assert g.rss_mib_per_cycle <= leaks.LIMIT_MIB_PER_CYCLE, (
        f"{mode}: {g.rss_mib_per_cycle:+.4f} MiB per cycle ({g.before.rss_kib} -> {g.after.rss_kib} KiB)"
    )
