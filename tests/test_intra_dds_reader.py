"""cloneguard.container.intra.dds_reader: a DDS subscription that sees publisher gids.

Real rclpy on real Fast DDS (the harness plugin's loopback-only UDP profile,
intraprocess delivery off, no shared memory), two nodes in this process on
one executor, a ROS domain leased for the module. Each test has topics of its
own, so nothing one test publishes reaches another's readers.
"""

from __future__ import annotations

import time
from collections import Counter

import pytest
from rclpy.exceptions import InvalidHandle, InvalidTopicNameException
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from ros_support import ros_nodes
from std_msgs.msg import String, UInt8MultiArray

from cloneguard.container.intra.dds_reader import GID_SIZE, GidFilteredReader, publisher_gid

# Reliable and keeping everything: a test that counts messages must not lose
# any to history depth.
QOS = QoSProfile(
    history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE
)
DEADLINE = 20.0  # seconds any single condition may take


@pytest.fixture(scope="module")
def ros():
    with ros_nodes("dds_reader_test_pub", "dds_reader_test_sub") as ((pub_node, sub_node), executor):
        yield pub_node, sub_node, executor


def spin_until(executor, condition, timeout=DEADLINE) -> bool:
    """Spin until condition() holds; False if it still does not at the deadline."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            return condition()
        executor.spin_once(timeout_sec=0.05)
    return True


def wait_matched(executor, publishers, reader, timeout=DEADLINE) -> None:
    """Both ends discovered: volatile messages published before are lost."""
    assert spin_until(
        executor,
        lambda: (
            reader.get_publisher_count() == len(publishers) and all(p.get_subscription_count() >= 1 for p in publishers)
        ),
        timeout,
    ), "publishers and reader did not match"


class Recorder:
    """Callback and drop_from that remember what they saw, in order."""

    def __init__(self, drop=lambda gid: False):
        self.messages: list = []
        self.offered: list[bytes] = []  # every gid drop_from was asked about
        self._drop = drop

    def __call__(self, msg) -> None:
        self.messages.append(msg)

    def drop_from(self, gid: bytes) -> bool:
        assert isinstance(gid, bytes) and len(gid) == GID_SIZE
        self.offered.append(gid)
        return self._drop(gid)


def test_publisher_gid_is_16_stable_distinct_bytes_matching_the_graph(ros):
    pub_node, _, _ = ros
    a = pub_node.create_publisher(String, "gid_check", QOS)
    b = pub_node.create_publisher(String, "gid_check", QOS)
    try:
        gid_a, gid_b = publisher_gid(a), publisher_gid(b)
        assert GID_SIZE == 16
        assert isinstance(gid_a, bytes) and len(gid_a) == 16 and len(gid_b) == 16
        assert gid_a != gid_b
        assert publisher_gid(a) == gid_a and publisher_gid(a.handle) == gid_a
        # The ROS graph's endpoint gids (rmw_get_publishers_info_by_topic) are
        # the same bytes, found independently of our C.
        infos = pub_node.get_publishers_info_by_topic("/gid_check")
        graph = {bytes(info.endpoint_gid[:16]) for info in infos}
        assert graph == {gid_a, gid_b}
    finally:
        pub_node.destroy_publisher(a)
        pub_node.destroy_publisher(b)
    with pytest.raises(InvalidHandle):
        publisher_gid(a)


def test_reader_gets_every_message_of_two_publishers_with_their_gids(ros):
    pub_node, sub_node, executor = ros
    topic = "all_from_two"
    a = pub_node.create_publisher(String, topic, QOS)
    b = sub_node.create_publisher(String, topic, QOS)  # one on each node
    rec = Recorder()
    reader = GidFilteredReader(sub_node, String, topic, QOS, rec, drop_from=rec.drop_from)
    try:
        assert reader.topic_name == f"/{topic}"
        # The executor must not take from the handle itself: it is not an
        # rclpy Subscription of any node, only our waitable is on the node.
        assert all(s.handle is not reader.handle for s in sub_node.subscriptions)
        assert reader in list(sub_node.waitables)
        wait_matched(executor, [a, b], reader)
        gids = {"A": publisher_gid(a), "B": publisher_gid(b)}
        n = 25
        for i in range(n):
            a.publish(String(data=f"A-{i}"))
            b.publish(String(data=f"B-{i}"))
        assert spin_until(executor, lambda: len(rec.messages) >= 2 * n), f"got {len(rec.messages)} of {2 * n}"
        spin_until(executor, lambda: False, timeout=0.3)  # nothing more may come
        texts = [m.data for m in rec.messages]
        assert sorted(texts) == sorted([f"A-{i}" for i in range(n)] + [f"B-{i}" for i in range(n)])
        # Each publisher's messages in the order it sent them.
        assert [t for t in texts if t[0] == "A"] == [f"A-{i}" for i in range(n)]
        assert [t for t in texts if t[0] == "B"] == [f"B-{i}" for i in range(n)]
        # Nothing dropped: drop_from was asked once per message, in delivery
        # order, with the sending publisher's gid.
        assert reader.dropped == 0 and reader.received == 2 * n
        assert len(rec.offered) == 2 * n
        assert [gids[t[0]] for t in texts] == rec.offered
    finally:
        reader.destroy()
        pub_node.destroy_publisher(a)
        sub_node.destroy_publisher(b)


def test_messages_from_a_dropped_publisher_are_counted_not_delivered(ros):
    pub_node, sub_node, executor = ros
    topic = "drop_one"
    a = pub_node.create_publisher(String, topic, QOS)
    b = pub_node.create_publisher(String, topic, QOS)
    gid_a = publisher_gid(a)
    rec = Recorder(drop=lambda gid: gid == gid_a)
    reader = GidFilteredReader(sub_node, String, topic, QOS, rec, drop_from=rec.drop_from)
    try:
        wait_matched(executor, [a, b], reader)
        n_a, n_b = 15, 10
        for i in range(max(n_a, n_b)):
            if i < n_a:
                a.publish(String(data=f"A-{i}"))
            if i < n_b:
                b.publish(String(data=f"B-{i}"))
        assert spin_until(executor, lambda: len(rec.offered) >= n_a + n_b), f"saw {len(rec.offered)} of {n_a + n_b}"
        spin_until(executor, lambda: False, timeout=0.3)
        assert [m.data for m in rec.messages] == [f"B-{i}" for i in range(n_b)]
        assert reader.dropped == n_a
        assert reader.received == n_b
        assert Counter(rec.offered) == Counter({gid_a: n_a, publisher_gid(b): n_b})
    finally:
        reader.destroy()
        pub_node.destroy_publisher(a)
        pub_node.destroy_publisher(b)


def test_16_mib_message_round_trips_intact_and_the_buffer_is_reused(ros):
    pub_node, sub_node, executor = ros
    topic = "big"
    pub = pub_node.create_publisher(UInt8MultiArray, topic, QOS)
    rec = Recorder()
    reader = GidFilteredReader(sub_node, UInt8MultiArray, topic, QOS, rec, drop_from=rec.drop_from)
    try:
        wait_matched(executor, [pub], reader)
        size = 16 * 1024 * 1024
        # Not periodic in any power of two: a misplaced fragment would show.
        payload = bytes((i * 7 + i // 251) & 0xFF for i in range(65521)) * (size // 65521 + 1)
        payload = payload[:size]
        pub.publish(UInt8MultiArray(data=payload))
        # A small message after the big one, in the buffer grown for it: the
        # message's length, not the buffer's capacity, is what is taken (the
        # deserializer would not notice trailing bytes; taken_bytes does).
        pub.publish(UInt8MultiArray(data=b"tail"))
        assert spin_until(executor, lambda: len(rec.messages) >= 2, timeout=60), f"got {len(rec.messages)} of 2"
        big, tail = rec.messages
        assert len(big.data) == size
        assert big.data.tobytes() == payload
        assert tail.data.tobytes() == b"tail"
        assert rec.offered == [publisher_gid(pub)] * 2
        assert reader.taken_bytes == (
            len(serialize_message(UInt8MultiArray(data=payload)))
            + len(serialize_message(UInt8MultiArray(data=b"tail")))
        )
        assert reader.dropped == 0
    finally:
        reader.destroy()
        pub_node.destroy_publisher(pub)


def test_destroy_leaves_the_node_and_executor_usable(ros):
    pub_node, sub_node, executor = ros
    topic = "destroyed"
    pub = pub_node.create_publisher(String, topic, QOS)
    rec = Recorder()
    reader = GidFilteredReader(sub_node, String, topic, QOS, rec, drop_from=rec.drop_from)
    wait_matched(executor, [pub], reader)
    pub.publish(String(data="before"))
    assert spin_until(executor, lambda: len(rec.messages) == 1)

    reader.destroy()
    reader.destroy()  # idempotent
    assert reader not in list(sub_node.waitables)
    # The DDS reader is gone: the publisher stops matching it.
    assert spin_until(executor, lambda: pub.get_subscription_count() == 0), (
        "the destroyed reader's DDS endpoint is still matched"
    )
    pub.publish(String(data="after destroy"))  # to nobody
    spin_until(executor, lambda: False, timeout=0.3)
    assert [m.data for m in rec.messages] == ["before"]

    # The node still works: a plain subscription and a new reader on the topic.
    plain: list = []
    sub = sub_node.create_subscription(String, topic, lambda m: plain.append(m.data), QOS)
    rec2 = Recorder()
    reader2 = GidFilteredReader(sub_node, String, topic, QOS, rec2, drop_from=rec2.drop_from)
    try:
        assert spin_until(executor, lambda: pub.get_subscription_count() == 2)
        pub.publish(String(data="again"))
        assert spin_until(executor, lambda: plain == ["again"] and len(rec2.messages) == 1)
        assert rec2.messages[0].data == "again"
        assert [m.data for m in rec.messages] == ["before"]
    finally:
        reader2.destroy()
        sub_node.destroy_subscription(sub)
        pub_node.destroy_publisher(pub)


def test_an_error_in_drop_from_surfaces_after_the_messages_before_it(ros):
    """The batch's earlier messages are delivered, then spin_once raises; the
    message drop_from failed on is lost, the reader goes on."""
    pub_node, sub_node, executor = ros
    topic = "drop_from_raises"
    pub = pub_node.create_publisher(String, topic, QOS)
    asked = []

    def drop_from(gid):
        asked.append(gid)
        if len(asked) == 2:
            raise ValueError("bus unavailable")
        return False

    rec = Recorder()
    reader = GidFilteredReader(sub_node, String, topic, QOS, rec, drop_from=drop_from)
    errors = []

    def spin_recording_errors():
        try:
            executor.spin_once(timeout_sec=0.05)
        except RuntimeError as exc:
            errors.append(exc)

    try:
        wait_matched(executor, [pub], reader)
        for i in range(3):
            pub.publish(String(data=f"m{i}"))
        deadline = time.monotonic() + DEADLINE
        while len(rec.messages) < 2 and time.monotonic() < deadline:
            spin_recording_errors()
        assert [m.data for m in rec.messages] == ["m0", "m2"]
        assert len(errors) == 1 and isinstance(errors[0].__cause__, ValueError)
        assert "bus unavailable" in str(errors[0]) and reader.topic_name in str(errors[0])
        assert len(asked) == 3 and reader.dropped == 0
    finally:
        reader.destroy()
        pub_node.destroy_publisher(pub)


def test_invalid_topic_is_rejected_like_create_subscription(ros):
    _, sub_node, _ = ros
    before = list(sub_node.waitables)
    with pytest.raises(InvalidTopicNameException):
        GidFilteredReader(sub_node, String, "not a topic!", QOS, print, drop_from=lambda gid: False)
    assert list(sub_node.waitables) == before
