"""Command line of the harness: ``python -m cloneguard.harness SUBCOMMAND ...``.

    compare RUN_A RUN_B [--fail-on-regression] [--test z|wilson] [--alpha A]
    render RUN [-o OUT.html]
    merge RUN RUN ... --out DIR [--allow-mixed-commits]
    reproduce FAULT [--profile P] [--allocator A] [--seed S] [--trials N]
    summary RUN [--hang-chars N]

RUN is a report directory, its report.json, or reports/latest.

Adding a subcommand: write ``_add_NAME(subparsers)``, which creates its
parser and calls ``set_defaults(func=run_NAME)``, and ``run_NAME(args) ->
exit code``; then append ``_add_NAME`` to ``SUBCOMMANDS``.
"""

from __future__ import annotations

import argparse
import sys


def _add_compare(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "compare",
        help="compare two runs' survival rates and latencies",
        description="Per scenario: survival rate A -> B with counts and significance, "
        "median latency A -> B per series, and scenarios only in one run.",
    )
    p.add_argument("run_a", metavar="RUN_A", help="report directory or report.json (the baseline)")
    p.add_argument("run_b", metavar="RUN_B", help="report directory or report.json (the new run)")
    p.add_argument(
        "--fail-on-regression", action="store_true", help="exit 1 if any survival rate got significantly worse"
    )
    p.add_argument(
        "--test",
        dest="method",
        choices=("z", "wilson"),
        default="z",
        help="significance: z = two-proportion z-test (default), "
        "wilson = non-overlapping 95%% Wilson intervals (stricter)",
    )
    p.add_argument("--alpha", type=float, default=0.05, help="significance level of the z-test (default 0.05)")
    p.set_defaults(func=run_compare)


def run_compare(args: argparse.Namespace) -> int:
    from .report.compare import compare_reports, format_comparison
    from .report.model import load_report

    a, b = load_report(args.run_a), load_report(args.run_b)
    comparison = compare_reports(a, b, method=args.method, alpha=args.alpha)
    print(format_comparison(comparison))
    if args.fail_on_regression and comparison.regressions:
        print(f"FAIL: {len(comparison.regressions)} scenario(s) significantly worse", file=sys.stderr)
        return 1
    return 0


def _add_render(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("render", help="re-render report.html from report.json")
    p.add_argument("run", metavar="RUN", help="report directory or report.json")
    p.add_argument(
        "-o", "--output", default=None, help="where to write the HTML (default: report.html beside report.json)"
    )
    p.set_defaults(func=run_render)


def run_render(args: argparse.Namespace) -> int:
    from .report.model import load_report
    from .report.render import write_html

    report = load_report(args.run)
    print(write_html(report, args.output))
    return 0


def _add_merge(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser(
        "merge",
        help="join the reports of shards (--shard K/N) and of other seeds into one report",
        description="Join the reports of one suite's runs (shards of a run, runs of other --seed "
        "values): trials put together by scenario (runs of several seeds numbered anew, "
        "seed by seed), every expectation judged on all of them, hangs and diagnoses kept; "
        "a trial run twice is refused; writes report.json, "
        "report.html and junit.xml. Exit 1 if a scenario failed or an expectation "
        "is not met.",
    )
    p.add_argument("runs", metavar="RUN", nargs="+", help="report directories or report.json files")
    p.add_argument("--out", required=True, help="directory for the merged report")
    p.add_argument(
        "--allow-mixed-commits", action="store_true", help="merge runs of different commits (refused by default)"
    )
    p.set_defaults(func=run_merge)


def run_merge(args: argparse.Namespace) -> int:
    from .report.merge import merge_reports, write_merged
    from .report.model import load_report

    merged = merge_reports([load_report(r) for r in args.runs], allow_mixed_commits=args.allow_mixed_commits)
    out = write_merged(merged, args.out)
    summary = merged.summary()
    failed = [s for s in merged.scenarios if s.outcome in ("failed", "error")]
    print(
        f"merged {len(args.runs)} run(s): {summary['tests']} scenario(s), {summary['trials']} trial(s) "
        f"{summary['trial_outcomes']}; expectations {summary['expectations']}"
    )
    print(f"report: {out / 'report.html'}")
    for s in failed:
        print(f"FAILED {s.nodeid}: {s.message}", file=sys.stderr)
    return 1 if failed else 0


def _add_reproduce(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    from .reproduce import add_parser

    add_parser(subparsers)


def _add_summary(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = subparsers.add_parser("summary", help="a report as Markdown: the trials table and every non-survival")
    p.add_argument("run", metavar="RUN", help="report directory or report.json")
    p.add_argument("--hang-chars", type=int, default=240, help="how much of each diagnosis to quote")
    p.set_defaults(func=run_summary)


def run_summary(args: argparse.Namespace) -> int:
    from .report.model import load_report
    from .report.summary import markdown

    print(markdown(load_report(args.run), hang_chars=args.hang_chars), end="")
    return 0


SUBCOMMANDS = [_add_compare, _add_render, _add_merge, _add_reproduce, _add_summary]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m cloneguard.harness", description="cloneguard harness tools")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for add in SUBCOMMANDS:
        add(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (OSError, ValueError) as exc:
        print(f"python -m cloneguard.harness {args.command}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
