"""Range checks for the demo components' parameters: a bad value fails the
load with a message that says the accepted range."""

from __future__ import annotations

import math

# A timer period in seconds: below a millisecond a demo timer would only
# burn a CPU (and under a nanosecond rclpy rounds it to 0: fire forever).
PERIOD_RANGE_S = (0.001, 3600.0)


def period(value: float, name: str = "period") -> float:
    """A timer period in seconds, within PERIOD_RANGE_S."""
    low, high = PERIOD_RANGE_S
    if not (math.isfinite(value) and low <= value <= high):
        raise ValueError(f"parameter '{name}' must be between {low:g} and {high:g} seconds, got {value!r}")
    return value


def count(value: int, name: str, maximum: int = 2**62) -> int:
    """A non-negative count, at most ``maximum``."""
    if not 0 <= value <= maximum:
        raise ValueError(f"parameter '{name}' must be between 0 and {maximum}, got {value!r}")
    return value
