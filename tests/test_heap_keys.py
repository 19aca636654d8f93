"""Memory protection keys over node heaps (--pkeys: container/isolated/
heapkeys.c): a stray write into another node's heap kills the writer
alone; what nodes write of each other's legitimately never faults; and
where the CPU or kernel has no keys, --pkeys is refused, saying why."""

from __future__ import annotations

import re

import pytest
from cloneguard_interfaces.msg import ComponentEvent
from std_msgs.msg import UInt64

from cloneguard.faults import PACKAGE as TESTRIG
from cloneguard.harness.skips import heap_keys_missing

KEYS = ["--isolated", "--jemalloc", "--pkeys"]
NO_KEYS = ["--isolated", "--jemalloc", "--no-pkeys"]  # they are on by default on jemalloc
MISSING = heap_keys_missing()
needs_keys = pytest.mark.skipif(MISSING is not None, reason=f"--pkeys: {MISSING}")


@pytest.mark.skipif(MISSING is None, reason="this machine has memory protection keys: nothing to refuse")
def test_pkeys_is_refused_where_there_are_none(container_factory):
    proc = container_factory.start(KEYS)
    assert proc.wait(timeout=60) == 1
    assert "--pkeys is unavailable here: the CPU or kernel has no memory protection keys" in proc.log_text()


def test_keys_are_on_by_default_wherever_the_cpu_has_them(container_factory):
    """No flag: jemalloc and the guard, the isolated defaults, and keys
    wherever the CPU and kernel have them (a wild write is caught);
    elsewhere the log says they are off and why, and the container serves
    as before."""
    proc = container_factory.start(["--isolated"])
    client = container_factory.connect(proc)
    victim = client.load_ok(TESTRIG, "faults::HeapVictim")
    log = proc.log_text()
    if MISSING is not None:
        assert "memory protection keys over node heaps: off (the CPU has no memory protection keys" in log
        return
    assert re.search(r"memory protection keys over node heaps: \d+ keys \(", log), log
    # The victim makes its buffer at its first check: the writer, which
    # looks it up as it is built, comes after one (issue 35: loaded 15 ms
    # after the victim, it found none, on a CPU with keys).
    client.subscribe(UInt64, "/heap_victim/checks").wait_count(1, timeout=10)
    writer = client.load_ok(TESTRIG, "faults::WildWriter", parameters={"delay": 0.05})
    crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=writer.unique_id, timeout=30)
    assert "protection-key violation: wrote into /heap_victim (pid " in crashed.error_message
    assert [uid for uid, _ in client.list()] == [victim.unique_id]


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (
            ["--isolated", "--allocator", "glibc"],
            "node heaps are keyed on jemalloc only (the default; not --allocator glibc)",
        ),
        (NO_KEYS, "--no-pkeys"),
        (["--isolated", "--jemalloc", "--no-alloc-guard"], "--no-alloc-guard"),
    ],
    ids=["glibc", "no-pkeys", "no-alloc-guard"],
)
def test_the_log_says_why_keys_are_off(args, why, container_factory):
    proc = container_factory.start(args)
    container_factory.connect(proc).load_ok(TESTRIG, "faults::HeapVictim")
    if "glibc" in args and MISSING is not None:  # the CPU's reason comes first
        why = "the CPU has no memory protection keys"
    assert f"memory protection keys over node heaps: off ({why}" in proc.log_text()


@pytest.mark.parametrize("profile", ["per-node", "shared"])
@needs_keys
def test_a_wild_write_kills_the_writer_and_leaves_the_victim_intact(profile, container_factory):
    proc = container_factory.start([*KEYS, "--profile", profile])
    client = container_factory.connect(proc)
    assert "memory protection keys over node heaps: " in proc.log_text()
    client.load_ok(TESTRIG, "faults::HeapVictim")
    checks = client.subscribe(UInt64, "/heap_victim/checks")
    checks.wait_count(5, timeout=10)
    writer = client.load_ok(TESTRIG, "faults::WildWriter", parameters={"delay": 0.05})
    crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=writer.unique_id, timeout=10)
    assert crashed.exit_signal == 11  # SIGSEGV
    assert "protection-key violation: wrote into /heap_victim (pid " in crashed.error_message
    assert "the write did not land" in crashed.error_message
    seen = len(checks)
    checks.wait_count(seen + 5, timeout=10)  # the victim goes on checking ...
    assert checks.messages()[-1].data == 0  # ... and never found its buffer changed
    assert [name for _, name in client.list()] == ["/heap_victim"]


@pytest.mark.parametrize("profile", ["per-node", "shared"])
@pytest.mark.parametrize("keys", [pytest.param(True, marks=needs_keys), False], ids=["pkeys", "no-pkeys"])
def test_nodes_freeing_and_holding_each_others_memory_never_fault(keys, profile, container_factory):
    """Cross-node traffic that is legitimate: native blocks one node
    allocates and another frees (handed over: the freer links the block
    into the owner's stack, under the owner's key), and 256 KiB
    intra-process messages (Python objects, their buffers in the
    publisher's shared arena) whose reference counts another node changes
    and whose last reference it drops."""
    proc = container_factory.start([*(KEYS if keys else NO_KEYS), "--profile", profile])
    client = container_factory.connect(proc)
    client.load_ok(TESTRIG, "faults::MallocDrain")
    client.load_ok(TESTRIG, "faults::MallocHammer", parameters={"delay": 0.0})
    intra = {"use_intra_process_comms": True}
    client.load_ok(TESTRIG, "faults::PayloadHolder", extra_arguments=intra)
    client.load_ok(TESTRIG, "faults::PayloadPublisher", parameters={"period": 0.002}, extra_arguments=intra)
    freed = client.subscribe(UInt64, "/malloc_drain/freed")
    released = client.subscribe(UInt64, "/payload_holder/released")
    # Bounds for an emulated CPU too (the keys are tested under QEMU where
    # the host has none): seconds here, minutes there.
    freed.wait_for(lambda m: m.data > 10_000, 60, "the drain freeing the hammer's blocks")
    released.wait_for(lambda m: m.data > 20, 60, "the holder releasing the publisher's messages")
    deaths = [e for e in client.events.messages() if e.event_type == ComponentEvent.CRASHED]
    assert deaths == [], [e.error_message for e in deaths]


@needs_keys
def test_writers_that_die_one_after_another_never_get_the_victims_key(container_factory):
    """Every faulting writer quarantines its slot, so each new one takes a
    slot never used before; slot s's key is fixed (key index (s-1) % 14:
    x86_64's 15 keys less the container's own). A new slot is the unused
    one whose key the fewest live slots hold, so the victim's key is never
    handed out again while fewer than 15 node processes live and other
    keys have unused slots: here 60 writers in a row (more than one key's
    36 slots), each one caught. Before, the 14th took the victim's key;
    then, once one key's slots were used up, the first unused slot of any
    key did."""
    proc = container_factory.start([*KEYS, "--profile", "shared"])
    client = container_factory.connect(proc)
    victim = client.load_ok(TESTRIG, "faults::HeapVictim")
    checks = client.subscribe(UInt64, "/heap_victim/checks")
    checks.wait_count(5, timeout=10)
    victim_key = None
    for i in range(60):
        writer = client.load_ok(TESTRIG, "faults::WildWriter", node_name=f"writer{i}", parameters={"delay": 0.05})
        crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=writer.unique_id, timeout=30)
        assert "protection-key violation: wrote into /heap_victim" in crashed.error_message, (i, crashed.error_message)
        key = crashed.error_message.split("(key ")[1].split(")")[0]
        assert victim_key in (None, key)  # the key named is the victim's heap's
        victim_key = key
    seen = len(checks)
    checks.wait_count(seen + 5, timeout=30)
    assert checks.messages()[-1].data == 0
    assert [uid for uid, _ in client.list()] == [victim.unique_id]


@needs_keys
def test_a_write_into_the_allocator_guards_tables_kills_the_writer_alone(container_factory):
    """The guard's tables (every slot's arena, hooks and hand-over stack)
    are under the container's own key: no node process may write them but
    through the guard's own bracketed stores."""
    proc = container_factory.start(KEYS)
    client = container_factory.connect(proc)
    writer = client.load_ok(TESTRIG, "faults::WildWriter", parameters={"delay": 0.05, "target": "allocator-tables"})
    crashed = client.wait_for_event(ComponentEvent.CRASHED, unique_id=writer.unique_id, timeout=30)
    assert crashed.exit_signal == 11
    assert "protection-key violation: wrote into the container's allocator tables at 0x" in crashed.error_message
    client.load_ok(TESTRIG, "faults::HeapVictim")  # the guard still makes slots and arenas
    checks = client.subscribe(UInt64, "/heap_victim/checks")
    checks.wait_count(5, timeout=30)


@pytest.mark.parametrize("keys", [pytest.param(True, marks=needs_keys), False], ids=["pkeys", "no-pkeys"])
def test_the_garbage_collector_freeing_every_nodes_cycles_never_faults(keys, container_factory):
    """Three nodes make reference cycles that hold blocks of their own
    (keyed) native heaps, linked to each other's, and call gc.collect()
    themselves: the collector runs on a container thread
    (isolated/collector.py), whose finalizers free every node's blocks
    (handed back to their owners); nothing faults."""
    proc = container_factory.start(KEYS if keys else NO_KEYS)
    client = container_factory.connect(proc)
    for i in range(3):
        client.load_ok(TESTRIG, "faults::CycleMaker", node_name=f"cycles{i}")
    freed = client.subscribe(UInt64, "/cycles0/freed")
    freed.wait_for(lambda m: m.data > 20_000, 120, "the collector finalizing the nodes' cycles")
    deaths = [e for e in client.events.messages() if e.event_type == ComponentEvent.CRASHED]
    assert deaths == [], [e.error_message for e in deaths]
    assert len(client.list()) == 3
