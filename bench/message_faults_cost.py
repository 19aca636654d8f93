"""What message faults cost when none is set: a container with the rig's
engine loaded (faults::MessageFaults, no rule) against one without it.

    python -m cloneguard.bench.message_faults_cost              # 20 pairs
    python -m cloneguard.bench.message_faults_cost --n 40 --count 200

Each pair starts two isolated containers side by side, A with the engine
loaded and B without (the engine is in the interpreter for good once
loaded, so the two cannot share one), and runs in each, A and B in turn
(which goes first alternates), the intra benchmark's pair of nodes
(bench.intra: bench::PayloadSource and bench::PayloadSink, a 1 KiB message
every ``period``) over intra-process delivery and over DDS: publish →
callback latency, the median of ``count`` messages per side. Per pair the
ratio A ÷ B; the goal is judged on the median of those ratios and its 95%
interval (the sign test's, bench.figures.median_interval).
"""

from __future__ import annotations

import statistics
import sys

from cloneguard.faults import PACKAGE as RIG
from cloneguard.faults.message_rules import ENGINE_NODE_NAME

from .cli import DEFAULT_OUT, arg_parser, command_line, finish
from .figures import fmt_ms
from .goals import Goal, goal_median_ratio
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
                resp = started["A"].client.load(RIG, "faults::MessageFaults", node_name=ENGINE_NODE_NAME)
                if not resp.success:
                    raise RuntimeError(f"the engine did not load: {resp.error_message}")
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
    errors = [e for r in pairs for e in r["errors"]]
    result = Result(
        name=NAME,
        title=TITLE,
        command=command_line(NAME, {k: v for k, v in params.items() if k != "out"}),
        params=params,
        tables=[table],
        goals=goals,
        notes=[
            f"Containers: component_container --isolated ({label(isolated_default())}), two at a time; A has "
            "the rig's message-fault engine loaded, which patches every take of the interpreter, with no rule.",
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
