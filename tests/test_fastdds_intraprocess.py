"""An isolated container turns Fast DDS's intraprocess delivery off,
whatever its profile says (docs/fastdds.md): with it on, a node process's
thread delivers into another participant's readers by calling into them,
inside their locks, and a node killed there leaves them held."""

from __future__ import annotations

import subprocess
import sys

from cloneguard_interfaces.msg import ComponentEvent
from std_msgs.msg import UInt64

from cloneguard.harness.process import NO_SHM_PROFILE, process_environment


def full_profile(tmp_path):
    """The harness's profile with intraprocess delivery FULL (Fast DDS's default)."""
    text = NO_SHM_PROFILE.read_text()
    assert "<intraprocess_delivery>OFF</intraprocess_delivery>" in text
    path = tmp_path / "fastdds_intraprocess_full.xml"
    path.write_text(text.replace("<intraprocess_delivery>OFF<", "<intraprocess_delivery>FULL<"))
    return path


def test_the_setting_fast_dds_reads_at_each_match_is_off_after_the_call(tmp_path, domain_id):
    """What Fast DDS consults whenever a writer matches a reader of the same
    process (XMLProfileManager::library_settings), read back."""
    code = (
        "import rclpy; from rclpy.node import Node; rclpy.init(); Node('n');"
        "from cloneguard.container.isolated.dds_defaults import intraprocess_off;"
        "print(intraprocess_off(), intraprocess_off())"
    )
    env = process_environment(domain_id, fastdds_profile=full_profile(tmp_path))
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["FULL", "OFF"]


def test_a_profile_with_it_on_is_overridden_and_said_and_nodes_still_talk(container_factory, tmp_path):
    proc = container_factory.start(["--isolated"], fastdds_profile=full_profile(tmp_path))
    client = container_factory.connect(proc)
    assert "Fast DDS intraprocess delivery turned off (the profile had FULL)" in proc.log_text()
    client.load_ok("cloneguard", "cloneguard::Listener")
    client.load_ok("cloneguard", "cloneguard::Talker", parameters={"period": 0.01})
    received = client.subscribe(UInt64, "/listener/received")
    received.wait_for(lambda m: m.data >= 100, 60, "the listener receiving the talker's messages over DDS")
    deaths = [e for e in client.events.messages() if e.event_type == ComponentEvent.CRASHED]
    assert deaths == [], [e.error_message for e in deaths]


def test_a_profile_with_it_off_is_left_alone_and_not_warned_about(container_factory):
    proc = container_factory.start(["--isolated"])
    container_factory.connect(proc)
    assert "intraprocess delivery turned off" not in proc.log_text()
