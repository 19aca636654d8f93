"""What message faults cost when none is set: a container with the rig's
engine loaded (faults::MessageFaults, no rule) against one without it.

    python -m cloneguard.bench.message_faults_cost              # 20 pairs
    python -m cloneguard.bench.message_faults_cost --n 40 --count 200

Each pair starts two isolated containers side by side, A with the engine
loaded and B without (the engine is in the interpreter for good once
loaded, so the two cannot share one; B loads an idle node of the same
weight in its place, a MessageProbe on a topic nobody publishes, so that
only the engine's hooks differ), and runs in each, A and B in turn
(which goes first alternates), the intra benchmark's pair of nodes
(bench.intra: bench::PayloadSource and bench::PayloadSink, a 1 KiB message
every ``period``) over intra-process delivery and over DDS: publish →
callback latency, the median of ``count`` messages per side. Per pair the
ratio A ÷ B; the goal is judged on the median of those ratios and its 95%
interval (the sign test's, bench.figures.median_interval). Where that
interval is wider than the goal, the second table settles it: what the
hooks add to each message, timed in this process, against B's latency.
"""

from __future__ import annotations

import statistics
import sys
from typing import Any

from cloneguard.faults import PACKAGE as RIG
from cloneguard.faults.message_rules import ENGINE_NODE_NAME

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ms
from .goals import Goal, goal_at_most, goal_median_ratio
from .intra import plan, run_pair
from .modes import isolated_default, label
from .results import Result, Table, summary_row
from .session import Session

NAME = "message_faults_cost"
TITLE = "Message faults off: the engine loaded with no rule vs no engine"
GOAL_PCT = 2.0
TRANSPORTS = {"intra-plain": "intra-process delivery, 1 KiB", "dds": "DDS, 1 KiB"}
SIZE = 1024


def _params(count: int, period: float) -> dict:
    return {"count": count, "warmup": 5, "period": period, "large_period": period, "dds_large_period": 0.5,
            "dds_large_count": 20, "burst": 2, "burst_bytes": 1 << 30, "burst_seconds": 0.2, "settle": 0.2}  # fmt: skip


def measure(n: int, count: int, period: float, keep_logs: bool) -> tuple[list[dict], list[str]]:
    """Per pair, by transport: A's and B's median latency (ms), or an error."""
    p = _params(count, period)
    session = Session(NAME, keep_logs=keep_logs)
    pairs: list[dict] = []
    try:
        for i in range(n):
            sides = ("A", "B") if i % 2 == 0 else ("B", "A")
            started = {side: session.start(isolated_default()) for side in sides}
            rec: dict = {"first": sides[0], "errors": [], "ms": {t: {} for t in TRANSPORTS}}
            try:
                # B gets a node of its own weight that patches nothing (an idle
                # MessageProbe), so that only the engine's hooks differ.
                for side, plugin, params in (("A", "faults::MessageFaults", {}),
                                             ("B", "faults::MessageProbe", {"topic": "/nothing_here"})):  # fmt: skip
                    resp = started[side].client.load(RIG, plugin, node_name=ENGINE_NODE_NAME, parameters=params)
                    if not resp.success:
                        raise RuntimeError(f"{plugin} did not load: {resp.error_message}")
                for k, transport in enumerate(TRANSPORTS):
                    for side in sides if k % 2 == 0 else sides[::-1]:
                        d = run_pair(started[side], 2 * k + (side == "B"), plan(SIZE, transport, p), p)
                        if d["error"]:
                            rec["errors"].append(f"pair {i}, {side}, {transport}: {d['error']}")
                        else:
                            rec["ms"][transport][side] = statistics.median(d["sink"]["latency_us"]) / 1e3
            finally:
                for side in sides:
                    session.stop(started[side])
            pairs.append(rec)
    finally:
        problems = session.close()
    return pairs, problems


def hook_ns(calls: int = 1_000_000) -> float:
    """What one of the engine's hooks adds to a delivery with no rule set,
    in ns, timed in this process: the engine's own intra-process delivery
    hook (faults/messages.py, _faulty_intra_deliver: the rules' lookup, then
    the call through) against the call it makes, with that call a no-op for
    both. A message meets one hook over DDS (the take) and two
    intra-process (the hand-over and the delivery), each the same lookup."""
    import timeit
    from types import SimpleNamespace

    from cloneguard.faults import messages

    # All the hook reads of a subscription; the delivery it calls, a no-op.
    subscription: Any = SimpleNamespace(topic="/bench_intra/payload_1", intra=True)
    original = messages._intra_deliver
    messages._intra_deliver = lambda self, msg: None
    try:
        hooked = min(timeit.repeat(lambda: messages._faulty_intra_deliver(subscription, 1), number=calls, repeat=5))
        plain = min(timeit.repeat(lambda: messages._intra_deliver(subscription, 1), number=calls, repeat=5))
    finally:
        messages._intra_deliver = original
    return (hooked - plain) / calls * 1e9


def judge(measure: str, ratios: list[float]) -> Goal:
    goal = f"≤ {GOAL_PCT:g}% slower with the engine loaded, no rule (95% interval)"
    return goal_median_ratio(goal, measure, ratios, 1.0 + GOAL_PCT / 100.0)


def run(*, n: int = 20, count: int = 100, period: float = 0.01, out=DEFAULT_OUT, keep_logs: bool = False,
        quiet: bool = False) -> Result:  # fmt: skip
    params = {"n": n, "count": count, "period": period, "out": str(out)}
    pairs, problems = measure(n, count, period, keep_logs)
    table = Table(
        f"Publish → callback latency, median per side (ms), {n} pairs of containers",
        ["transport", "pairs", "engine loaded (A)", "no engine (B)", "A ÷ B: median [95% interval]"],
    )
    goals, summary = [], []
    for transport, what in TRANSPORTS.items():
        both = [r["ms"][transport] for r in pairs if len(r["ms"][transport]) == 2]
        ratios = [d["A"] / d["B"] for d in both]
        goal = judge(what, ratios)
        goals.append(goal)
        a = statistics.median(d["A"] for d in both) if both else None
        b = statistics.median(d["B"] for d in both) if both else None
        table.add(what, len(both), fmt_ms(a), fmt_ms(b), goal.measured)
        summary.append(summary_row(NAME, f"{what}: publish → callback", "engine loaded ÷ none", None,
                                   median=goal.measured, goal=goal.goal, verdict=goal.verdict))  # fmt: skip
    added = hook_ns()
    hooks = Table("What the engine's hooks add to a message, no rule set (timed in-process, best of 5 × 10⁶ calls)",
                  ["transport", "hooks a message meets", "added (ns)", "of B's median latency"])  # fmt: skip
    for (transport, what), n_hooks in zip(TRANSPORTS.items(), (2, 1), strict=True):
        both = [r["ms"][transport]["B"] for r in pairs if "B" in r["ms"][transport]]
        share = n_hooks * added / (statistics.median(both) * 1e6) if both else None
        hooks.add(what, n_hooks, f"{n_hooks * added:.0f}", "–" if share is None else f"{100 * share:.3f}%")
        goals.append(goal_at_most(f"hooks add ≤ {GOAL_PCT:g}% of a message's latency", what,
                                  None if share is None else 100 * share, GOAL_PCT, "%"))  # fmt: skip
    errors = [e for r in pairs for e in r["errors"]]
    result = Result(
        name=NAME,
        title=TITLE,
        command=command_line(NAME, {k: v for k, v in params.items() if k != "out"}),
        params=params,
        tables=[table, hooks],
        goals=goals,
        notes=[
            f"Containers: component_container --isolated ({label(isolated_default())}), two at a time; A has "
            "the rig's message-fault engine loaded, which patches every take of the interpreter, with no rule; "
            "B an idle MessageProbe in its place (a node of the same weight that patches nothing).",
            "Each side's figure is the median of its messages' latencies; which side runs first alternates.",
            *(["Pairs that failed: " + "; ".join(errors)] if errors else []),
        ],
        summary=summary,
        raw={"pairs": pairs},
        cleanup=problems,
    )
    return finish(result, out, quiet=quiet)


def main(argv=None) -> int:
    parser = arg_parser(NAME, TITLE)
    parser.add_argument("--n", type=int, default=20, help="pairs of containers (default 20)")
    parser.add_argument("--count", type=int, default=100, help="messages per side and transport (default 100)")
    parser.add_argument("--period", type=float, default=0.01, help="s between messages (default 0.01)")
    args = parser.parse_args(argv)
    result = run(n=args.n, count=args.count, period=args.period, out=args.out, keep_logs=args.keep_logs)
    return 0 if not result.cleanup else 1


if __name__ == "__main__":
    sys.exit(main())
