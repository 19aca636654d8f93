"""Message faults do what they say, measured from outside (issue 39): a
Talker sends "m <n>" on /chatter at 50 Hz and a subscriber inside the
container republishes what it heard (harness/message_probe.py); each
trial puts one fault, drawn from its seed, on that subscriber for a
second, and the harness compares what was sent with what was heard.
Per-node and shared profiles, over DDS and intra-process delivery."""

import math
import statistics

import pytest

from cloneguard.harness.message_probe import ChatterProbe, number
from cloneguard.harness.report.stats import wilson_interval, z_for
from cloneguard.harness.schedule import Corrupt, Delay, Drop, Duplicate, Partition, Reorder
from cloneguard.harness.system_trials import Measure

CELLS = [(profile, transport) for profile in ("per-node", "shared") for transport in ("dds", "intra")]
cells = pytest.mark.parametrize("profile, transport", CELLS, ids=[f"{p}-{t}" for p, t in CELLS])
FAULT_S = 1.0
AT_LEAST = 0.99
TRIAL_SLACK_MS = 5.0
OVER_TRIALS_MIN = 30
#: a trial's dropped share against the asked probability: a gross error
#: only (a correct engine falls outside once in a million trials)
TRIAL_SHARE_CONFIDENCE = 1 - 1e-6


def probe(system_factory, profile: str, transport: str) -> ChatterProbe:
    return ChatterProbe(system_factory, profile, intra=transport == "intra")


@cells
def test_a_drop_loses_the_share_it_asks_for(system_factory, system_trials, resilience, profile, transport):
    w = probe(system_factory, profile, transport)
    drawn: list[tuple[int, int, float]] = []  # each trial's (dropped, seen, asked)

    def trial(t):
        p = round(t.rng.uniform(0.2, 0.8), 2)
        missing_before = set(w.missing())
        [fault] = w.system.inject(Drop("/chatter", FAULT_S, probability=p))
        lost = set(w.missing()) - missing_before
        seen, dropped = fault.counts.get("seen", 0), fault.counts.get("dropped", 0)
        assert dropped == len(lost), f"the engine dropped {dropped}, the subscriber missed {len(lost)}"
        drawn.append((dropped, seen, p))
        low, high = wilson_interval(dropped, seen, TRIAL_SHARE_CONFIDENCE)
        assert low <= p <= high, f"{dropped} of {seen} dropped, asked {p}: interval {low:.2f}-{high:.2f}"
        return {"dropped minus asked": Measure(100 * (dropped / seen - p), "points")}

    system_trials(w.system, trial, fault="drop a drawn share (20-80%) for 1 s",
                  claim="exactly the messages the engine dropped are missing, and their share is the asked "
                        "probability (within its 1-in-a-million interval each trial, 99.9% over the trials)",
                  at_least=AT_LEAST)  # fmt: skip
    # The share over every trial: the draws are the engine's, one a message,
    # so the dropped count is a sum of independent Bernoulli(p) draws, with
    # mean sum(p * seen) and variance sum(p * (1 - p) * seen). A trial alone
    # (~50 messages) is judged only against a gross error: at 99.9% a
    # correct engine missed 1 trial in 1,000 (seed 3901, trial 3: 20 of 50
    # at 0.63), which 3 quick trials a cell would make a flaky test.
    dropped = sum(d for d, _, _ in drawn)
    mean = sum(p * n for _, n, p in drawn)
    sd = math.sqrt(sum(p * (1 - p) * n for _, n, p in drawn))
    said = f"dropped {dropped} of {sum(n for _, n, _ in drawn)} over {len(drawn)} trials, {mean:.1f} expected"
    if len(drawn) < OVER_TRIALS_MIN:
        resilience.note(f"{said}; the share over the trials is judged on {OVER_TRIALS_MIN} trials or more (--deep)")
    else:
        z = (dropped - mean) / sd
        assert abs(z) <= z_for(0.999), f"{said}: {z:+.2f} standard deviations off (99.9%: within {z_for(0.999):.2f})"


@cells
def test_a_delay_adds_what_it_asks_for(system_factory, system_trials, resilience, profile, transport):
    w = probe(system_factory, profile, transport)

    errors: list[float] = []  # each trial's added minus asked (ms)

    def lateness_ms(since: int) -> list[float]:
        sent_at = w.sent_at()
        return sorted((r.at_ns - sent_at[n]) / 1e6 for r, n in _heard(w, since) if n in sent_at)

    def trial(t):
        delay_s = t.rng.choice([0.05, 0.1, 0.2, 0.3])
        missing_before = set(w.missing())
        base = statistics.median(lateness_ms(max(0, len(w.heard) - 20)))  # the last 20 before: the path's own
        since = len(w.heard)
        [fault] = w.system.inject(Delay("/chatter", FAULT_S, delay_s=delay_s))
        assert set(w.missing()) == missing_before, "a delayed message was lost"
        delayed = [x for x in lateness_ms(since) if x > base + delay_s * 500]
        assert len(delayed) == fault.counts["delayed"], f"{len(delayed)} heard late, {fault.counts} delayed"
        added = statistics.median(delayed) - base
        errors.append(added - delay_s * 1e3)
        assert abs(errors[-1]) <= TRIAL_SLACK_MS, f"median added {added:.2f} ms for {delay_s * 1e3:g} ms asked"
        return {"added minus asked": errors[-1]}

    system_trials(w.system, trial, fault="delay by a drawn 50-300 ms for 1 s",
                  claim=f"no message lost, each trial's median added latency within {TRIAL_SLACK_MS:g} ms of "
                        "the asked delay, and over the trials within 1 ms", at_least=AT_LEAST)  # fmt: skip
    # The claim on the median over the trials, judged on OVER_TRIALS_MIN
    # or more (--deep): a trial's own median lies between -0.5 and +1.3 ms
    # (100 trials a cell, shared profile, with the holder's lead: median
    # +0.22 ms intra, +0.36 ms DDS), and a median of 3 is no estimate of it.
    overall = statistics.median(errors)
    said = f"added minus asked, median over {len(errors)} trials: {overall:+.2f} ms"
    if len(errors) < OVER_TRIALS_MIN:
        resilience.note(f"{said}; the 1 ms claim is judged on {OVER_TRIALS_MIN} trials or more (--deep)")
    else:
        assert abs(overall) <= 1.0, said


@cells
def test_duplicates_and_reorderings_are_counted_and_nothing_is_lost(system_factory, system_trials, profile, transport):
    w = probe(system_factory, profile, transport)

    def trial(t):
        dup, heard = _heard_under(w, Duplicate("/chatter", FAULT_S / 2, every=t.rng.choice([1, 2, 3])))
        twice = sum(heard.count(n) == 2 for n in set(heard))
        assert twice == dup.counts["duplicated"] > 0, f"{twice} heard twice, {dup.counts}"
        reorder, heard = _heard_under(w, Reorder("/chatter", FAULT_S / 2, window_s=t.rng.choice([0.1, 0.2])))
        assert sorted(heard) == list(range(min(heard), max(heard) + 1)), "a reordered message lost or doubled"
        inversions = sum(a > b for a, b in zip(heard, heard[1:], strict=False))
        assert inversions > 0 and reorder.counts["reordered"] == reorder.counts["seen"], reorder.counts
        return {"inversions": Measure(inversions, "count")}

    system_trials(w.system, trial, fault="duplicate every 1st-3rd, then reorder 100-200 ms windows",
                  claim="every duplicate counted, every reordered message heard once, out of order",
                  at_least=AT_LEAST)  # fmt: skip


@cells
def test_corruption_reaches_its_subscriber_only(system_factory, system_trials, profile, transport):
    w = probe(system_factory, profile, transport)

    def trial(t):
        corrupt = Corrupt("/chatter", FAULT_S / 2, fields={"data": "m -1"}, every=t.rng.choice([1, 2]))
        fault, heard = _heard_under(w, corrupt)
        corrupted = heard.count(-1)
        assert corrupted == fault.counts["corrupted"] > 0, f"{corrupted} heard corrupted, {fault.counts}"
        assert -1 not in w.sent_numbers(), "the publisher's own message was changed"

    system_trials(w.system, trial, fault="corrupt a field of every 1st or 2nd message for 0.5 s",
                  claim="the subscriber gets exactly the corrupted messages counted; the publisher's are intact",
                  at_least=AT_LEAST)  # fmt: skip


@cells
def test_a_partition_is_total_and_heals(system_factory, system_trials, profile, transport):
    w = probe(system_factory, profile, transport)

    def trial(t):
        missing_before = set(w.missing())
        seconds = round(t.rng.uniform(0.3, 1.0), 2)
        [cut] = w.system.inject(Partition(publishers=["/talker"], subscribers=["/message_probe"], seconds=seconds))
        lost = sorted(set(w.missing()) - missing_before)
        assert cut.counts.get("dropped", 0) == cut.counts.get("seen", 0) == len(lost) > 0, (cut.counts, len(lost))
        sent_at = w.sent_at()
        after = [n for n in lost if sent_at.get(n, 0) > cut.end_ns + 50_000_000]
        assert after == [], f"still cut 50 ms after the partition ended: {after}"

    system_trials(w.system, trial, fault="partition the talker from the subscriber for a drawn 0.3-1 s",
                  claim="every message between them lost while it lasts, none from 50 ms after it ends",
                  at_least=AT_LEAST)  # fmt: skip


def _heard_under(w: ChatterProbe, fault):
    """Inject the fault; it, once ended, and the numbers heard meanwhile and
    until the subscriber settled."""
    since = len(w.heard)
    [injected] = w.system.inject(fault)
    w.settle()
    return injected, w.heard_numbers(since)


def _heard(w: ChatterProbe, since: int):
    return [(r, number(r.msg)) for r in w.heard_items(since)]
