"""Range checks for the demo components' parameters: a bad value fails the
load with a message that says the accepted range."""
from __future__ import annotations

import math

MAX_PERIOD_S = 3600.0


def period(value: float, name: str = "period") -> float:
    """A timer period in seconds: finite, > 0, <= MAX_PERIOD_S."""
    if not (math.isfinite(value) and 0.0 < value <= MAX_PERIOD_S):
        raise ValueError(f"parameter '{name}' must be more than 0 and at most "
                         f"{MAX_PERIOD_S:g} seconds, got {value!r}")
    return value


def count(value: int, name: str, maximum: int = 2**62) -> int:
    """A non-negative count, at most ``maximum``."""
    if not 0 <= value <= maximum:
        raise ValueError(f"parameter '{name}' must be between 0 and {maximum}, got {value!r}")
    return value
