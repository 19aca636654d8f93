"""Message-fault rules and the fate each gives a message (faults/message_rules.py):
which messages a rule hits, replayed by its seed; what a hit does."""

import math

import pytest
from sensor_msgs.msg import LaserScan
from std_msgs.msg import String

from cloneguard.faults.message_rules import Rule, RuleError, corrupt, fate, rules_from_text, rules_to_text
from cloneguard.harness.schedule import Corrupt, Delay, Drop, Partition, stale


def fates(rule: Rule, n: int, subscriber="/planner", publisher="/lidar", now=100.0):
    counts: dict = {}
    return [fate([rule], "/planner|/scan", subscriber, publisher, counts, now) for _ in range(n)]


def test_a_probability_is_drawn_from_the_seed_and_replays():
    rule = Rule("a", "drop", "/scan", seed=7, probability=0.5)
    first = [f.drop for f in fates(rule, 2000)]
    assert first == [f.drop for f in fates(rule, 2000)]  # the same seed: the same messages
    assert first != [f.drop for f in fates(Rule("a", "drop", "/scan", seed=8, probability=0.5), 2000)]
    # 2,000 fair draws: 1,000 ± 4.4 standard deviations
    assert 900 < sum(first) < 1100
    # The draws depend on the salt, not the id the engine gave the rule.
    salted = [f.drop for f in fates(Rule("b", "drop", "/scan", seed=7, probability=0.5, salt="a"), 2000)]
    assert salted == first


def test_every_nth_message_is_hit():
    assert [i + 1 for i, f in enumerate(fates(Rule("a", "drop", "/scan", every=3), 10)) if f.drop] == [3, 6, 9]


def test_a_rule_hits_only_its_subscribers_and_publishers():
    rule = Rule("a", "drop", "/scan", subscribers=("/planner",), publishers=("/lidar",))
    assert all(f.drop for f in fates(rule, 5))
    assert not any(f.drop for f in fates(rule, 5, subscriber="/mapper"))
    assert not any(f.drop for f in fates(rule, 5, publisher="/other_lidar"))
    assert not any(f.drop for f in fates(rule, 5, publisher=None))  # a publisher not known is not theirs


def test_a_delay_makes_the_message_due_later_by_its_delay_and_jitter():
    [f] = fates(Rule("a", "delay", "/scan", delay_s=0.3), 1)
    assert f.due == pytest.approx(100.3) and not f.drop
    dues = [f.due for f in fates(Rule("a", "delay", "/scan", delay_s=0.3, jitter_s=0.1), 200)]
    assert all(100.3 <= d < 100.4 for d in dues) and len(set(dues)) > 150


def test_a_reorder_window_holds_its_messages_until_it_closes_in_a_drawn_order():
    out = fates(Rule("a", "reorder", "/scan", window_s=0.25), 20, now=100.1)
    assert {f.due for f in out} == {100.25}
    orders = [f.order for f in out]
    assert sorted(orders) != orders  # shuffled
    assert orders == [f.order for f in fates(Rule("a", "reorder", "/scan", window_s=0.25), 20, now=100.1)]


def test_duplicates_and_corruptions_add_up():
    rules = [Rule("a", "duplicate", "/scan"), Rule("b", "corrupt", "/scan", fields={"ranges": math.nan})]
    [f] = [fate(rules, "s", "/planner", None, {}, 0.0)]
    assert f.copies == 2 and f.corrupt == {"ranges": math.nan} and [r.id for r in f.hit] == ["a", "b"]


def test_corrupt_sets_numbers_sequences_and_stale_stamps():
    scan = LaserScan(range_max=10.0, ranges=[1.0, 2.0, 3.0])
    scan.header.stamp.sec, scan.header.stamp.nanosec = 100, 250_000_000
    corrupt(scan, {"ranges": math.nan, "range_max": 0, "header.stamp": stale(1.5)})
    assert len(scan.ranges) == 3 and all(math.isnan(r) for r in scan.ranges)
    assert scan.range_max == 0.0
    assert (scan.header.stamp.sec, scan.header.stamp.nanosec) == (98, 750_000_000)
    assert corrupt(String(data="hello"), {"data": "garbage"}).data == "garbage"
    with pytest.raises(RuleError, match="no field 'rnages'"):
        corrupt(scan, {"rnages": 0.0})


@pytest.mark.parametrize(
    "rule, why",
    [
        (dict(id="a", kind="explode", topic="/scan"), "kind must be one of"),
        (dict(id="a", kind="drop", topic="scan"), "full name"),
        (dict(id="a", kind="drop", topic="/scan", probability=1.5), "probability"),
        (dict(id="a", kind="delay", topic="/scan"), "a delay is 0-60 s"),
        (dict(id="a", kind="reorder", topic="/scan"), "window"),
        (dict(id="a", kind="corrupt", topic="/scan"), "needs fields"),
        (dict(id="a", kind="partition", topic="*", publishers=["/lidar"]), "publishers and subscribers"),
        (dict(id="a", kind="drop", topic="/scan", subscribers=["planner"]), "full names"),
    ],
)
def test_a_bad_rule_is_refused_saying_why(rule, why):
    with pytest.raises(RuleError, match=why):
        Rule.from_json(rule)


def test_the_rules_go_as_json_and_come_back_alike():
    rules = [
        Rule("a", "corrupt", "/scan", seed=3, fields={"ranges": -math.inf, "header.stamp": stale(2)}),
        Rule("b", "partition", "*", publishers=("/lidar",), subscribers=("/planner",)),
    ]
    back = rules_from_text(rules_to_text(rules))
    assert [r.to_json() for r in back] == [r.to_json() for r in rules]
    assert back[0].fields["ranges"] == -math.inf
    for text, why in [("{", "not JSON"), ('{"id": "a"}', "JSON list"), ('[{"id": "a", "kind": "drop"}]', "needs id"),
                      ('[{"id": "a", "kind": "drop", "topic": "/x", "colour": 1}]', "unknown rule field"),
                      ('[{"id": "a", "kind": "drop", "topic": "/x"}, {"id": "a", "kind": "drop", "topic": "/y"}]',
                       "same id")]:  # fmt: skip
        with pytest.raises(RuleError, match=why):
            rules_from_text(text)


def test_schedule_entries_make_their_rules_and_refuse_bad_ones_at_once():
    rule = Delay("/odom", 2.0, delay_s=0.3, subscribers=["/planner"]).rule("m1", 5)
    assert (rule.kind, rule.delay_s, rule.subscribers, rule.seed) == ("delay", 0.3, ("/planner",), 5)
    assert Drop("/scan", 4.0, probability=0.5).describe() == "drop 50% on /scan for 4 s"
    part = Partition(publishers=["/lidar"], subscribers=["/planner"], seconds=2.0)
    assert (part.topic, part.describe()) == ("*", "partition 100% on * from /lidar to /planner for 2 s")
    assert "ranges=NaN" in Corrupt("/scan", 1.0, fields={"ranges": math.nan}).describe()
    with pytest.raises(RuleError, match="a delay is"):
        Delay("/odom", 2.0, delay_s=0.0)
    with pytest.raises(ValueError, match="lasts 0-3600 s"):
        Drop("/scan", 0.0)
