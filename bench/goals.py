"""A benchmark's goals: what was asked, the figure measured, and whether it
was met or by how much it was missed."""

from __future__ import annotations

from dataclasses import dataclass

from .figures import fmt_ms, fmt_ratio


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
