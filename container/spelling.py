"""What a name that matched nothing may have meant: the names there are,
closest to it first, for a log line next to a "not found".

Closeness is difflib's similarity ratio (matching characters over total
length, ``SequenceMatcher.ratio``), case ignored; equally close names keep
alphabetical order, so the same request always lists them the same way.
"""

from __future__ import annotations

from collections.abc import Iterable
from difflib import SequenceMatcher

# Enough for a typo's target to be among them, few enough to read in one line.
SHOWN = 10


def closest_first(wanted: str, names: Iterable[str]) -> list[str]:
    """Every one of ``names``, the closest to ``wanted`` first."""
    matcher = SequenceMatcher(None, b="")
    matcher.set_seq2(wanted.casefold())  # seq2 is the one SequenceMatcher indexes: once

    def distance(name: str) -> tuple[float, str]:
        matcher.set_seq1(name.casefold())
        return -matcher.ratio(), name

    return sorted(names, key=distance)


def closest_listed(wanted: str, names: Iterable[str], shown: int = SHOWN) -> str:
    """``closest_first`` as text: the first ``shown`` names, comma separated,
    and how many more there are."""
    ranked = closest_first(wanted, names)
    rest = len(ranked) - shown
    return ", ".join(ranked[:shown]) + (f" (and {rest} more)" if rest > 0 else "")
