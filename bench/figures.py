"""The benchmarks' figures: n, median and p90 of a sample, nanoseconds to
milliseconds, ratios of medians, and how each is written in a table.

Kept apart from ``harness.report.stats`` (whose quantile is the same type 7
interpolation): its arithmetic differs in the last bits and it turns whole
numbers into floats, so the reports' raw figures would change."""

from __future__ import annotations

import math
import statistics


def stats(values: list[float]) -> dict:
    """n, median, p90 (inclusive quantiles), min, max of ``values``."""
    vals = sorted(v for v in values if v is not None and not math.isnan(v))
    if not vals:
        return {"n": 0, "median": None, "p90": None, "min": None, "max": None}
    p90 = statistics.quantiles(vals, n=10, method="inclusive")[-1] if len(vals) > 1 else vals[0]
    return {"n": len(vals), "median": statistics.median(vals), "p90": p90, "min": vals[0], "max": vals[-1]}


def ms(ns_values: list[int]) -> list[float]:
    return [v / 1e6 for v in ns_values]


def fmt_ms(x: float | None) -> str:
    if x is None:
        return "–"
    if x >= 100:
        return f"{x:.0f}"
    if x >= 10:
        return f"{x:.1f}"
    if x >= 1:
        return f"{x:.2f}"
    return f"{x:.3f}"


def fmt_ratio(x: float | None) -> str:
    if x is None or math.isinf(x) or math.isnan(x):
        return "–"
    return f"{x:.0f}×" if x >= 10 else f"{x:.1f}×"


def ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or b <= 0:
        return None
    return a / b


def median_interval(values: list[float], confidence: float = 0.95) -> tuple[float, float, float] | None:
    """The distribution-free interval for the median of ``values``: the
    order statistics x(k) and x(n+1-k), k the largest with
    P(Binomial(n, 1/2) ≤ k-1) ≤ (1 - confidence)/2 (the sign test's
    interval). (low, high, its exact coverage), or None when there are too
    few values for any (fewer than 6 at 95%)."""
    xs = sorted(values)
    n = len(xs)
    tail, k = 0.0, 0
    while k < n:
        p = math.comb(n, k) / 2.0**n
        if tail + p > (1.0 - confidence) / 2.0:
            break
        tail += p
        k += 1
    if k == 0:
        return None
    return xs[k - 1], xs[n - k], 1.0 - 2.0 * tail


def pct(ratio: float) -> str:
    """A ratio as a change: 1.034 -> "+3.4%"."""
    return f"{100.0 * (ratio - 1.0):+.1f}%"
