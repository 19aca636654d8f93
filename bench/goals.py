"""A benchmark's goals: what was asked, the figure measured, and whether it
was met or by how much it was missed."""

from __future__ import annotations

import statistics
from dataclasses import dataclass

from .figures import fmt_ms, fmt_ratio, median_interval, pct


@dataclass
class Goal:
    goal: str  # what was asked, e.g. "median ≤ 1 ms"
    measure: str  # what it is judged on
    measured: str  # the figure, formatted
    met: bool | None  # None: could not be measured
    verdict: str  # "met", or by how much it is missed

    def row(self) -> dict:
        return {"goal": self.goal, "judged on": self.measure, "measured": self.measured, "verdict": self.verdict}


def goal_at_most(goal: str, measure: str, value: float | None, limit: float, unit: str) -> Goal:
    if value is None:
        return Goal(goal, measure, "–", None, "not measured")
    shown = f"{fmt_ms(value)} {unit}"
    if value <= limit:
        return Goal(goal, measure, shown, True, "met")
    return Goal(
        goal, measure, shown, False, f"missed by {fmt_ms(value - limit)} {unit} ({fmt_ratio(value / limit)} the goal)"
    )


def goal_at_least_ratio(goal: str, measure: str, value: float | None, target: float) -> Goal:
    if value is None:
        return Goal(goal, measure, "–", None, "not measured")
    if value >= target:
        return Goal(goal, measure, fmt_ratio(value), True, "met")
    short = target / value
    return Goal(
        goal,
        measure,
        fmt_ratio(value),
        False,
        f"missed: {fmt_ratio(value)} of {fmt_ratio(target)} "
        f"({f'{short:.2f}×' if short < 2 else fmt_ratio(short)} short)",
    )


def ratio_verdict(value: float, limit: float) -> str:
    """The verdict on a ratio that is to be at most ``limit``."""
    if value <= limit:
        return f"met ({fmt_ratio(value)})"
    return f"missed: {fmt_ratio(value)} against ≤ {fmt_ratio(limit)} ({value / limit:.1f}× over)"


def goal_ratio_at_most(goal: str, measure: str, value: float | None, limit: float) -> Goal:
    if value is None:
        return Goal(goal, measure, "–", None, "not measured")
    return Goal(goal, measure, fmt_ratio(value), value <= limit, ratio_verdict(value, limit))


def goal_median_ratio(goal: str, measure: str, ratios: list[float], limit: float) -> Goal:
    """A ratio of interleaved pairs (A ÷ B each) judged against ``limit``
    on its median's 95% interval: met if the interval ends at or below it,
    missed if it starts above it, else undecided."""
    if not ratios:
        return Goal(goal, measure, "–", None, "not measured")
    med, ci = statistics.median(ratios), median_interval(ratios)
    if ci is None:
        shown = f"{pct(med)} (n={len(ratios)})"
        return Goal(goal, measure, shown, None, f"undecided: {len(ratios)} pairs give no 95% interval (6 needed)")
    lo, hi, _ = ci
    shown = f"{pct(med)} [{pct(lo)}, {pct(hi)}] (n={len(ratios)})"
    if hi <= limit:
        return Goal(goal, measure, shown, True, f"met: the interval ends at {pct(hi)}")
    if lo > limit:
        return Goal(goal, measure, shown, False, f"missed: the interval starts at {pct(lo)}")
    return Goal(goal, measure, shown, None, f"undecided: the interval holds {pct(limit)}")
