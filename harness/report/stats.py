"""Statistics for crash-resilience reports: proportions with Wilson score
intervals, a two-proportion z-test, and latency summaries.

Only the standard library; everything here is a pure function of its inputs.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from statistics import NormalDist

#: Confidence level of every interval in the reports.
CONFIDENCE = 0.95


def z_for(confidence: float = CONFIDENCE) -> float:
    """The two-sided standard normal quantile for ``confidence`` (1.96 for 0.95)."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    return NormalDist().inv_cdf(0.5 + confidence / 2.0)


def wilson_interval(successes: int, trials: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """The Wilson score interval for ``successes`` out of ``trials``.

    With p = k/n and z the normal quantile:

        centre     = (p + z²/2n) / (1 + z²/n)
        half-width = z / (1 + z²/n) · sqrt(p(1-p)/n + z²/4n²)

    Unlike the normal approximation it stays inside [0, 1] and is sensible at
    k = 0 and k = n, which is where crash-survival rates usually are. With no
    trials nothing is known: (0, 1).
    """
    if trials < 0 or successes < 0 or successes > trials:
        raise ValueError(f"need 0 <= successes <= trials, got {successes}/{trials}")
    if trials == 0:
        return (0.0, 1.0)
    z = z_for(confidence)
    n = float(trials)
    p = successes / n
    z2 = z * z
    denom = 1.0 + z2 / n
    centre = (p + z2 / (2.0 * n)) / denom
    half = (z / denom) * math.sqrt(p * (1.0 - p) / n + z2 / (4.0 * n * n))
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return (low, high)


@dataclass(frozen=True)
class Proportion:
    """``successes`` of ``trials``, the rate (None without trials) and its Wilson interval."""

    successes: int
    trials: int
    rate: float | None
    low: float
    high: float

    def to_dict(self) -> dict:
        return asdict(self)


def percent(rate: float | None, none: str = "–") -> str:
    """A rate in percent: one decimal, or two significant digits between 0
    and 1% (a 95% upper bound of none in 9,000 trials is 0.043%, not 0.0%)."""
    if rate is None:
        return none
    value = rate * 100
    return f"{value:.2g}%" if 0 < value < 1 else f"{value:.1f}%"


def proportion(successes: int, trials: int, confidence: float = CONFIDENCE) -> Proportion:
    low, high = wilson_interval(successes, trials, confidence)
    rate = successes / trials if trials else None
    return Proportion(successes, trials, rate, low, high)


def intervals_overlap(a: Proportion, b: Proportion) -> bool:
    return a.low <= b.high and b.low <= a.high


def two_proportion_z_test(k1: int, n1: int, k2: int, n2: int) -> tuple[float, float]:
    """Pooled two-proportion z-test of p1 == p2; returns (z, two-sided p-value).

    z > 0 means the second proportion is lower. When both samples are all
    successes or all failures the pooled variance is 0 and there is no
    evidence of a difference: (0.0, 1.0). Raises ValueError without trials.
    """
    if n1 <= 0 or n2 <= 0:
        raise ValueError("both samples need at least one trial")
    p1, p2 = k1 / n1, k2 / n2
    pooled = (k1 + k2) / (n1 + n2)
    se = math.sqrt(pooled * (1.0 - pooled) * (1.0 / n1 + 1.0 / n2))
    if se == 0.0:
        return (0.0, 1.0)
    z = (p1 - p2) / se
    p_value = math.erfc(abs(z) / math.sqrt(2.0))
    return (z, p_value)


def quantile(sorted_values: Sequence[float], q: float) -> float:
    """The ``q`` quantile of already sorted values, linearly interpolated
    between closest ranks (the default of numpy and R's type 7)."""
    if not sorted_values:
        raise ValueError("quantile of no values")
    if not 0.0 <= q <= 1.0:
        raise ValueError(f"q must be in [0, 1], got {q!r}")
    pos = q * (len(sorted_values) - 1)
    lo = math.floor(pos)
    hi = min(lo + 1, len(sorted_values) - 1)
    frac = pos - lo
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * frac


@dataclass(frozen=True)
class LatencySummary:
    n: int
    min: float
    median: float
    p90: float
    p99: float
    max: float
    mean: float

    def to_dict(self) -> dict:
        return asdict(self)


def summarize(values: Iterable[float]) -> LatencySummary | None:
    """n, min, median, p90, p99, max and mean of ``values``; None if empty."""
    data = sorted(float(v) for v in values)
    if not data:
        return None
    return LatencySummary(
        n=len(data),
        min=data[0],
        median=quantile(data, 0.5),
        p90=quantile(data, 0.9),
        p99=quantile(data, 0.99),
        max=data[-1],
        mean=math.fsum(data) / len(data),
    )
