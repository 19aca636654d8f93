"""The bounded participant-listener wait (listenerwait.c): once installed,
every DDS participant deletion's infinite set_listener wait goes through it
(and still completes), so Fast DDS's spin there (eProsima/Fast-DDS#6513)
cannot happen. In a process of its own: it patches libfastrtps's GOT."""

import subprocess
import sys
import textwrap

import pytest

pytest.importorskip("cloneguard.container.isolated._clonecore")

SCRIPT = textwrap.dedent("""
    import logging, threading
    import rclpy
    from rclpy.context import Context
    from cloneguard.container.isolated import listener_wait

    assert listener_wait.waits_bounded() is None  # nothing installed yet
    rclpy.init()
    assert listener_wait.bound(logging.getLogger()) is True
    assert listener_wait.bound(logging.getLogger()) is True  # once only
    assert listener_wait.waits_bounded() == 0
    # Discovery traffic while participants go: peers that stay, and
    # deletions on two threads at once.
    peers = []
    for i in range(3):
        ctx = Context(); rclpy.init(context=ctx)
        peers.append((ctx, rclpy.create_node(f"peer{i}", context=ctx)))

    def churn(tag):
        for i in range(6):
            ctx = Context(); rclpy.init(context=ctx)
            node = rclpy.create_node(f"churn_{tag}_{i}", context=ctx)
            node.create_publisher(__import__("std_msgs.msg").msg.String, "chatter", 10)
            node.destroy_node(); ctx.try_shutdown(); ctx.destroy()

    threads = [threading.Thread(target=churn, args=(t,)) for t in "ab"]
    for t in threads: t.start()
    for t in threads: t.join()
    # Each deletion waits twice: rmw_fastrtps's set_listener(nullptr), and
    # Fast DDS's own in DomainParticipantImpl::disable.
    print("bounded", listener_wait.waits_bounded())
""")


def test_every_participant_deletion_waits_through_the_bounded_wait():
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "bounded 24" in proc.stdout, proc.stdout
