"""--node-announcement: the DDS participants of node processes re-announce
themselves at their own period (3 s by default in isolated mode),
the container's own at the profile's (100 ms in the harness's profile). Measured from outside, as DDS sees it:
the SPDP announcements that reach the domain's multicast group, counted
per participant (the RTPS header's GUID prefix)."""

import os
import re
import signal
import socket
import struct
import time
from collections import Counter

import pytest

SPDP_GROUP = "239.255.0.1"
WINDOW_S = 3.0


def spdp_port(domain_id: int) -> int:
    """The SPDP multicast port of a domain (RTPS 2.x: PB 7400, DG 250, d0 0)."""
    return 7400 + 250 * domain_id


def announcements(domain_id: int, seconds: float) -> Counter:
    """RTPS messages to the domain's SPDP multicast group, per GUID prefix."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind(("", spdp_port(domain_id)))
        mreq = struct.pack("4s4s", socket.inet_aton(SPDP_GROUP), socket.inet_aton("127.0.0.1"))
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
        sock.settimeout(0.2)
        seen: Counter = Counter()
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            if data[:4] == b"RTPS":
                seen[data[8:20]] += 1
        return seen
    finally:
        sock.close()


@pytest.mark.parametrize("container_args", [["--isolated", "--profile", "per-node", "--node-announcement", "1"]])
def test_node_participants_announce_at_their_own_period(client, container, domain_id):
    for i in range(3):
        client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name=f"hb{i}", parameters={"period": 1.0})
    assert "node processes' participants announce every 1 s (the container's own: 0.1 s)" in container.log_text()
    time.sleep(1.0)  # past the new participants' initial announcements (5 at 100 ms)
    seen = announcements(domain_id, WINDOW_S)
    # the container's participant and the harness's client: ~10 a second;
    # the three nodes' and the warm spare's: ~1 a second
    fast = sorted(n for n in seen.values() if n >= 0.6 * WINDOW_S / 0.1)
    slow = sorted(n for n in seen.values() if n <= 2 * WINDOW_S / 1.0)
    assert len(fast) == 2 and len(slow) == 4 and len(seen) == 6, seen


@pytest.mark.parametrize("container_args", [["--isolated", "--profile", "per-node", "--node-announcement", "0"]])
def test_at_0_every_participant_keeps_the_profiles_period(client, container, domain_id):
    client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name="hb0", parameters={"period": 1.0})
    time.sleep(1.0)
    seen = announcements(domain_id, WINDOW_S)
    assert len(seen) == 4 and all(n >= 0.6 * WINDOW_S / 0.1 for n in seen.values()), seen


# In a shared container too: a rule or a LoadNode may give a node a
# participant of its own.
@pytest.mark.parametrize("container_args", [["--isolated", "--profile", "per-node"], ["--isolated"]],
                         ids=["per-node", "shared"])  # fmt: skip
def test_the_isolated_default_is_3_s(client, container):
    assert "node processes' participants announce every 3 s (the container's own: 0.1 s)" in container.log_text()


@pytest.mark.parametrize("container_args", [[]])
def test_nothing_changes_in_thread_mode(client, container):
    client.list()
    assert "participants announce every" not in container.log_text()


@pytest.mark.parametrize("container_args", [["--isolated", "--profile", "per-node"]])
def test_a_load_can_ask_for_the_shared_profile_in_a_per_node_container(client, container, domain_id):
    """cloneguard.profile per load: the shared node adds no participant
    (counted on the wire), the per-node one does; both run, and the shared
    one's death leaves the rest going."""
    from cloneguard_interfaces.msg import ComponentEvent

    shared = client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name="hb_shared",
                            extra_arguments={"cloneguard.profile": "shared"})  # fmt: skip
    client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name="hb_own")
    time.sleep(1.0)  # past the new participants' initial announcements
    # the container's, the harness client's, the warm spare's and hb_own's: not hb_shared
    assert len(announcements(domain_id, WINDOW_S)) == 4
    assert sorted(name for _, name in client.list()) == ["/hb_own", "/hb_shared"]
    pid = next(ev.pid for ev in client.events.messages() if ev.unique_id == shared.unique_id)
    os.kill(pid, signal.SIGKILL)
    client.wait_for_event(ComponentEvent.CRASHED, unique_id=shared.unique_id)
    assert [name for _, name in client.list()] == ["/hb_own"]


@pytest.mark.parametrize(
    "container_args", [["--isolated", "--profile", "shared", "--profile-for", "/planning/*=per-node",
                        "--profile-for", "cloneguard::Talker=per-node"]]
)  # fmt: skip
def test_profile_rules_give_a_participant_to_the_nodes_they_name_only(client, container, domain_id):
    """--profile-for: the node under /planning and the Talker get a
    participant of their own (counted on the wire), the rest are built on
    the container's."""
    client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name="planner", node_namespace="/planning")
    client.load_ok("cloneguard", "cloneguard::Heartbeat", node_name="odometry")
    client.load_ok("cloneguard", "cloneguard::Talker")
    time.sleep(1.0)
    # the container's, the harness client's, /planning/planner's and the talker's
    assert len(announcements(domain_id, WINDOW_S)) == 4
    log = container.log_text()
    for name, profile in (("/planning/planner", "per-node"), ("/odometry", "shared"), ("/talker", "per-node")):
        assert re.search(rf"as {name} \(unique_id \d+, pid \d+, profile {profile}\)", log), (name, log)
