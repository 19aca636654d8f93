"""cloneguard.container.intra's component API in one process: two nodes, one executor.

Real rclpy and Fast DDS (loopback profile, a leased domain); endpoints are
made with ``intra_process=True`` (in a container, LoadNode's
``use_intra_process_comms`` decides).
"""

import threading
import time

import pytest
import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from ros_support import ros_nodes
from std_msgs.msg import String, UInt8MultiArray

from cloneguard.container import intra
from cloneguard.container.intra.api import LoanedMessage


@pytest.fixture
def ros():
    with ros_nodes("pub_node", "sub_node") as (nodes, executor):
        spinner = threading.Thread(target=executor.spin, daemon=True)
        spinner.start()
        yield nodes
        executor.shutdown()
        spinner.join(5)


class Inbox:
    def __init__(self):
        self.items, self.cond = [], threading.Condition()

    def __call__(self, msg):
        with self.cond:
            self.items.append(msg)
            self.cond.notify_all()

    def wait(self, n, timeout=10.0):
        with self.cond:
            assert self.cond.wait_for(lambda: len(self.items) >= n, timeout), f"{len(self.items)} of {n} messages"
        return self.items


def _wait(pred, what, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def test_the_subscriber_gets_the_published_object_itself(ros):
    pub_node, sub_node = ros
    inbox = Inbox()
    sub = intra.create_subscription(sub_node, String, "/a", inbox, 10, intra_process=True)
    pub = intra.create_publisher(pub_node, String, "/a", 10, intra_process=True)
    msgs = [String(data=f"m{i}") for i in range(5)]
    for m in msgs:
        pub.publish(m)
    got = inbox.wait(5)
    assert all(a is b for a, b in zip(got, msgs, strict=True))
    assert sub.received_intra == 5 and sub.received_dds == 0
    assert pub.sent_intra == 5 and pub.sent_dds == 0  # no one outside: DDS untouched


def test_keep_last_depth_bounds_the_queue(ros):
    pub_node, sub_node = ros
    inbox = Inbox()
    # Not spinning yet: make the subscription on a node outside the executor.
    idle = rclpy.create_node("idle_sub", context=pub_node.context)
    try:
        sub = intra.create_subscription(idle, String, "/b", inbox, 2, intra_process=True)
        pub = intra.create_publisher(pub_node, String, "/b", 10, intra_process=True)
        for i in range(5):
            pub.publish(String(data=str(i)))
        assert len(sub.queue) == 2 and sub.queue.dropped == 3
        sub._drain()
        assert [m.data for m in inbox.items] == ["3", "4"]
    finally:
        intra.api.destroy_endpoints(idle)
        idle.destroy_node()


def test_a_reliable_subscription_does_not_match_a_best_effort_publisher(ros):
    pub_node, sub_node = ros
    inbox = Inbox()
    intra.create_subscription(
        sub_node, String, "/c", inbox, QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE), intra_process=True
    )
    pub = intra.create_publisher(
        pub_node, String, "/c", QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT), intra_process=True
    )
    pub.publish(String(data="x"))
    assert pub.sent_intra == 0
    be_inbox = Inbox()
    intra.create_subscription(
        sub_node,
        String,
        "/c",
        be_inbox,
        QoSProfile(depth=5, reliability=ReliabilityPolicy.BEST_EFFORT),
        intra_process=True,
    )
    pub.publish(String(data="y"))
    assert [m.data for m in be_inbox.wait(1)] == ["y"] and inbox.items == []


def test_transient_local_is_refused_with_a_clear_error(ros):
    pub_node, _ = ros
    qos = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    with pytest.raises(ValueError, match="VOLATILE durability only"):
        intra.create_publisher(pub_node, String, "/d", qos, intra_process=True)


def test_publishing_the_wrong_type_raises(ros):
    pub_node, _ = ros
    pub = intra.create_publisher(pub_node, String, "/e", 10, intra_process=True)
    with pytest.raises(TypeError, match="expected String"):
        pub.publish(UInt8MultiArray())


def test_an_outside_subscriber_gets_dds_and_the_intra_one_each_message_once(ros):
    pub_node, sub_node = ros
    inbox, outside_inbox = Inbox(), Inbox()
    sub = intra.create_subscription(sub_node, String, "/f", inbox, 50, intra_process=True)
    # A plain rclpy subscription is "outside": not in the container's bus.
    outside = sub_node.create_subscription(String, "/f", outside_inbox, 50)
    pub = intra.create_publisher(pub_node, String, "/f", 50, intra_process=True)
    _wait(lambda: pub.get_subscription_count() == 2, "both DDS readers matched")
    for i in range(20):
        pub.publish(String(data=str(i)))
    assert [m.data for m in outside_inbox.wait(20)] == [str(i) for i in range(20)]
    _wait(lambda: sub.dropped_dds_duplicates == 20, "the 20 DDS copies dropped")
    assert [m.data for m in inbox.items] == [str(i) for i in range(20)]
    assert sub.received_intra == 20 and sub.received_dds == 0 and pub.sent_dds == 20
    sub_node.destroy_subscription(outside)


def test_a_plain_publisher_reaches_an_intra_subscription_over_dds(ros):
    pub_node, sub_node = ros
    inbox = Inbox()
    sub = intra.create_subscription(sub_node, String, "/g", inbox, 10, intra_process=True)
    plain = pub_node.create_publisher(String, "/g", 10)
    _wait(lambda: plain.get_subscription_count() == 1, "matched")
    plain.publish(String(data="over dds"))
    assert [m.data for m in inbox.wait(1)] == ["over dds"]
    assert sub.received_dds == 1 and sub.received_intra == 0


def test_a_loan_reaches_loaned_and_plain_subscriptions(ros):
    pub_node, sub_node = ros
    loaned_inbox, plain_inbox = Inbox(), Inbox()
    intra.create_subscription(
        sub_node, UInt8MultiArray, "/h", loaned_inbox, 10, intra_process=True, loaned_field="data"
    )
    intra.create_subscription(sub_node, UInt8MultiArray, "/h", plain_inbox, 10, intra_process=True)
    pub = intra.create_publisher(pub_node, UInt8MultiArray, "/h", 10, intra_process=True)
    payload = bytes(range(256)) * 4096  # 1 MiB
    loan = pub.loan(len(payload))
    loan.buffer[:] = payload
    template = UInt8MultiArray()
    template.layout.data_offset = 7
    pub.publish_loan(loan, template, "data")
    with pytest.raises(ValueError, match="read-only"):
        _ = loan.buffer  # sealed by publishing
    with pytest.raises(ValueError, match="already published"):
        pub.publish_loan(loan, template, "data")
    got = loaned_inbox.wait(1)[0]
    assert isinstance(got, LoanedMessage) and got.loaned
    assert got.message is template and bytes(got.payload) == payload
    with pytest.raises(TypeError):
        got.payload[0] = 0  # subscribers get read-only views
    full = plain_inbox.wait(1)[0]
    assert isinstance(full, UInt8MultiArray) and full.layout.data_offset == 7
    assert full.data.tobytes() == payload


def test_a_loaned_subscription_sees_dds_messages_through_the_same_interface(ros):
    pub_node, sub_node = ros
    inbox = Inbox()
    intra.create_subscription(sub_node, UInt8MultiArray, "/i", inbox, 10, intra_process=True, loaned_field="data")
    plain = pub_node.create_publisher(UInt8MultiArray, "/i", 10)
    _wait(lambda: plain.get_subscription_count() == 1, "matched")
    plain.publish(UInt8MultiArray(data=b"abc"))
    got = inbox.wait(1)[0]
    assert isinstance(got, LoanedMessage) and not got.loaned and bytes(got.payload) == b"abc"


def test_a_loan_can_only_stand_for_a_byte_array_field(ros):
    pub_node, sub_node = ros
    with pytest.raises(ValueError, match="a loan can only be a uint8"):
        intra.create_subscription(sub_node, String, "/j", print, 10, intra_process=True, loaned_field="data")
    with pytest.raises(ValueError, match="has no field 'pixels'"):
        intra.create_subscription(sub_node, UInt8MultiArray, "/j", print, 10, intra_process=True, loaned_field="pixels")


def test_endpoints_follow_the_load_they_were_made_in_and_are_forgotten_with_it(ros):
    pub_node, sub_node = ros
    bus = intra.get_bus()
    with intra.api.constructing(owner=4242, enabled=True):
        sub = intra.create_subscription(sub_node, String, "/k", print, 10)
    assert sub.intra and bus.subscriptions("/k")[0].owner == 4242
    off = intra.create_publisher(pub_node, String, "/k2", 10)  # no load: plain
    assert not off.intra
    assert bus.forget(4242) == 1 and bus.subscriptions("/k") == ()
