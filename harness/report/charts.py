"""Inline SVG charts for report.html: no scripts, no external resources.

Every text that goes into the SVG is escaped here; callers pass plain text.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from html import escape

from . import stats
from .model import TrialOutcome

OUTCOME_COLORS: dict[str, str] = {
    TrialOutcome.SURVIVED: "#2e9d4f",
    TrialOutcome.HUNG: "#e0a100",
    TrialOutcome.CRASHED: "#d13b3b",
    TrialOutcome.FAILED: "#7a6fb0",
    TrialOutcome.CORRUPTED: "#8c2d7a",
}

#: Dots drawn at most; the box, whiskers and median always use every value.
MAX_DOTS = 1500


def fmt_ms(value: float | None) -> str:
    """A latency in ms, with as many digits as its size deserves."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    a = abs(value)
    if a == 0:
        return "0"
    if a < 0.01:
        return f"{value:.2e}"
    if a < 10:
        return f"{value:.3g}" if a >= 1 else f"{value:.3f}".rstrip("0").rstrip(".")
    if a < 1000:
        return f"{value:.1f}"
    return f"{value:,.0f}"


def _tick_label(value: float) -> str:
    if value == 0:
        return "0"
    a = abs(value)
    if a >= 1e7 or a < 1e-3:
        return f"{value:.0e}"
    if a >= 1000:
        return f"{value:,.0f}"
    return f"{value:.6f}".rstrip("0").rstrip(".")


def _nice_step(rough: float) -> float:
    exponent = math.floor(math.log10(rough))
    base = 10.0**exponent
    for mult in (1.0, 2.0, 2.5, 5.0, 10.0):
        if rough <= mult * base * (1 + 1e-9):
            return mult * base
    return 10.0 * base


def linear_ticks(lo: float, hi: float, target: int = 6) -> list[float]:
    """Round tick values covering [lo, hi]; the first and last bound the axis."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError("ticks of a non-finite range")
    if hi < lo:
        lo, hi = hi, lo
    if hi == lo:
        pad = abs(lo) * 0.1 or 1.0
        lo, hi = (max(0.0, lo - pad) if lo >= 0 else lo - pad), hi + pad
    step = _nice_step((hi - lo) / max(1, target - 1))
    start = math.floor(lo / step + 1e-9) * step
    end = math.ceil(hi / step - 1e-9) * step
    count = int(round((end - start) / step))
    return [round(start + i * step, 12) for i in range(count + 1)]


def log_ticks(lo: float, hi: float) -> list[float]:
    """Powers of ten around [lo, hi] (lo > 0), with 2 and 5 in between when
    the range spans few decades."""
    first = math.floor(math.log10(lo) + 1e-9)
    last = math.ceil(math.log10(hi) - 1e-9)
    if last == first:
        last += 1
    ticks = []
    for e in range(first, last + 1):
        ticks.append(10.0**e)
        if last - first <= 2 and e < last:
            ticks.extend([2 * 10.0**e, 5 * 10.0**e])
    return sorted(ticks)


def _use_log(values: Sequence[float]) -> bool:
    lo, hi = min(values), max(values)
    return lo > 0 and hi / lo >= 100


def latency_strip(name: str, values: Sequence[float], unit: str = "ms", width: int = 640) -> str:
    """A strip plot of every value (in ``unit``; deterministic jitter) over
    a box from the 25th to the 75th percentile, whiskers to min and max, and
    the median marked and labelled. A logarithmic axis when values span
    >= 100x."""
    data = sorted(float(v) for v in values)
    if not data:
        return ""
    summary = stats.summarize(data)
    assert summary is not None  # data is not empty
    log = _use_log(data)
    if log:
        ticks = log_ticks(data[0], data[-1])
    else:  # start at 0 unless every value is far from it
        ticks = linear_ticks(0.0 if 0 <= data[0] <= 0.25 * data[-1] else data[0], data[-1])
    d0, d1 = ticks[0], ticks[-1]

    left, right = 14.0, 14.0
    top_label, band_top, band_bottom = 14.0, 22.0, 62.0
    axis_y, height = 70.0, 108
    plot_w = width - left - right

    def x(v: float) -> float:
        if log:
            frac = (math.log10(v) - math.log10(d0)) / (math.log10(d1) - math.log10(d0))
        else:
            frac = (v - d0) / (d1 - d0)
        return left + max(0.0, min(1.0, frac)) * plot_w

    mid = (band_top + band_bottom) / 2
    q1, q3 = stats.quantile(data, 0.25), stats.quantile(data, 0.75)
    median = summary.median
    title = (
        f"{name}: n={summary.n}, min {fmt_ms(summary.min)}, median {fmt_ms(median)}, "
        f"p90 {fmt_ms(summary.p90)}, p99 {fmt_ms(summary.p99)}, max {fmt_ms(summary.max)} {unit}"
    )
    out = [
        f'<svg class="chart" xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" role="img" aria-label="{escape(title)}">',
        f"<title>{escape(title)}</title>",
        f'<rect x="{left}" y="{band_top}" width="{plot_w:.1f}" height="{band_bottom - band_top}" class="band"/>',
    ]
    # grid and axis
    for t in ticks:
        tx = x(t)
        out.append(f'<line x1="{tx:.1f}" y1="{band_top}" x2="{tx:.1f}" y2="{band_bottom}" class="grid"/>')
        out.append(f'<line x1="{tx:.1f}" y1="{axis_y}" x2="{tx:.1f}" y2="{axis_y + 4}" class="axis"/>')
        anchor = "start" if tx <= left + 1 else "end" if tx >= left + plot_w - 1 else "middle"
        out.append(
            f'<text x="{tx:.1f}" y="{axis_y + 15}" text-anchor="{anchor}" class="tick">{escape(_tick_label(t))}</text>'
        )
    out.append(f'<line x1="{left}" y1="{axis_y}" x2="{left + plot_w:.1f}" y2="{axis_y}" class="axis"/>')
    axis_title = (f"{name} latency, ms" if unit == "ms" else f"{name}, {unit}") + (" (log scale)" if log else "")
    out.append(
        f'<text x="{left + plot_w / 2:.1f}" y="{height - 4}" text-anchor="middle" class="axis-title">'
        f"{escape(axis_title)}</text>"
    )
    # whiskers and box
    out.append(f'<line x1="{x(data[0]):.1f}" y1="{mid}" x2="{x(q1):.1f}" y2="{mid}" class="whisker"/>')
    out.append(f'<line x1="{x(q3):.1f}" y1="{mid}" x2="{x(data[-1]):.1f}" y2="{mid}" class="whisker"/>')
    for v in (data[0], data[-1]):
        out.append(f'<line x1="{x(v):.1f}" y1="{mid - 6}" x2="{x(v):.1f}" y2="{mid + 6}" class="whisker"/>')
    out.append(
        f'<rect x="{x(q1):.1f}" y="{mid - 11}" width="{max(1.0, x(q3) - x(q1)):.1f}" height="22" '
        f'class="box"><title>25th–75th percentile: {escape(fmt_ms(q1))}–{escape(fmt_ms(q3))} '
        f"{escape(unit)}</title></rect>"
    )
    # dots, in trial order with a golden-ratio jitter so the picture is reproducible
    step = max(1, math.ceil(len(values) / MAX_DOTS))
    dots = [float(v) for v in values][::step]
    with_titles = len(dots) <= 300
    for i, v in enumerate(dots):
        jitter = ((i * 0.6180339887498949) % 1.0) * 2.0 - 1.0
        cy = mid + jitter * ((band_bottom - band_top) / 2 - 4)
        tip = f"<title>{escape(fmt_ms(v))} {escape(unit)}</title>" if with_titles else ""
        out.append(f'<circle cx="{x(v):.1f}" cy="{cy:.1f}" r="2.6" class="dot">{tip}</circle>')
    # median
    mx = x(median)
    out.append(f'<line x1="{mx:.1f}" y1="{band_top - 2}" x2="{mx:.1f}" y2="{band_bottom + 2}" class="median"/>')
    label = f"median {fmt_ms(median)} {unit}"
    anchor = "start" if mx < left + 60 else "end" if mx > left + plot_w - 60 else "middle"
    out.append(f'<text x="{mx:.1f}" y="{top_label}" text-anchor="{anchor}" class="median-label">{escape(label)}</text>')
    out.append("</svg>")
    return "".join(out)


def outcome_bar(counts: dict[str, int], width: int = 320, height: int = 16) -> str:
    """A stacked bar of trial outcomes, in the order survived, hung, crashed, failed."""
    total = sum(counts.values())
    title = ", ".join(f"{k} {v}" for k, v in counts.items() if v) or "no trials"
    out = [
        f'<svg class="bar" xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" role="img" aria-label="{escape(title)}">',
        f"<title>{escape(title)}</title>",
        f'<rect x="0" y="0" width="{width}" height="{height}" fill="#eee"/>',
    ]
    xpos = 0.0
    for outcome, n in counts.items():
        if not n or not total:
            continue
        w = width * n / total
        color = OUTCOME_COLORS.get(outcome, "#999")
        out.append(
            f'<rect x="{xpos:.2f}" y="0" width="{w:.2f}" height="{height}" fill="{color}">'
            f"<title>{escape(outcome)}: {n}/{total}</title></rect>"
        )
        xpos += w
    out.append("</svg>")
    return "".join(out)
