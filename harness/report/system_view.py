"""The report's view of a scenario over a user's own System (seeded trials,
harness/system_trials.py): per watched topic, what it did across the
trials; a timeline of one trial (each topic's rate, the faults shaded);
and each trial's facts as words, its cause first.

Reads only what trials recorded in their details (``why``, ``faults``,
``topics``, ``timeline``); a scenario without them shows none of this.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from html import escape

from . import stats
from .model import Scenario, Trial, TrialOutcome


def e(value: object) -> str:
    return escape("" if value is None else str(value))


TOPIC_COLORS = ("#2f6fb3", "#2e9d4f", "#b35b2f", "#7a6fb0", "#8c2d7a", "#3a8c8c")


def has_system_view(s: Scenario) -> bool:
    return any("topics" in (t.details or {}) or "timeline" in (t.details or {}) for t in s.trials)


def _fmt(v: float | None, digits: int = 2) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def topics_table(s: Scenario) -> str:
    """One row a watched topic: over every trial, its rate (lowest and
    median) and its longest gap (median and worst), and how many trials
    saw no message at all."""
    per_topic: dict[str, list[dict]] = {}
    for t in s.trials:
        for name, facts in (t.details or {}).get("topics", {}).items():
            per_topic.setdefault(name, []).append(facts)
    if not per_topic:
        return ""
    rows = []
    for name, facts in per_topic.items():
        rates = sorted(f["rate_hz"] for f in facts)
        gaps = sorted(f["longest_gap_s"] for f in facts)
        silent = sum(1 for f in facts if f["messages"] == 0)
        rows.append(
            f'<tr><td class="mono">{e(name)}</td><td class="num">{len(facts)}</td>'
            f'<td class="num">{_fmt(rates[0], 1)}</td><td class="num">{_fmt(stats.quantile(rates, 0.5), 1)}</td>'
            f'<td class="num">{_fmt(stats.quantile(gaps, 0.5), 3)}</td><td class="num">{_fmt(gaps[-1], 3)}</td>'
            f'<td class="num">{silent}</td></tr>'
        )
    return (
        "<h4>Topics during the trials</h4>"
        '<table class="grid"><thead><tr><th>topic</th><th class="num">trials</th>'
        '<th class="num">lowest Hz</th><th class="num">median Hz</th>'
        '<th class="num">median longest gap s</th><th class="num">worst gap s</th>'
        '<th class="num">trials silent</th></tr></thead>'
        f"<tbody>{''.join(rows)}</tbody></table>"
    )


def nodes_table(s: Scenario) -> str:
    """One row a node and kind of fault it was given: in how many trials,
    and what became of those trials (the rest of the system's fate)."""
    rows: dict[tuple[str, str], dict[str, int]] = {}
    for t in s.trials:
        for key in dict.fromkeys((f["node"], f["kind"]) for f in (t.details or {}).get("faults", [])):
            counts = rows.setdefault(key, {})
            counts[t.outcome] = counts.get(t.outcome, 0) + 1
    if not rows:
        return ""
    outcomes = [o.value for o in TrialOutcome if any(o.value in c for c in rows.values())]
    head = "".join(f'<th class="num">{e(o)}</th>' for o in outcomes)
    body = "".join(
        f'<tr><td class="mono">{e(node)}</td><td>{e(kind)}</td><td class="num">{sum(c.values())}</td>'
        + "".join(f'<td class="num">{c.get(o, 0)}</td>' for o in outcomes)
        + "</tr>"
        for (node, kind), c in sorted(rows.items())
    )
    return (
        "<h4>Faults by node</h4>"
        '<table class="grid"><thead><tr><th>node</th><th>fault</th><th class="num">trials</th>'
        f"{head}</tr></thead><tbody>{body}</tbody></table>"
    )


def _timeline_trial(s: Scenario) -> Trial | None:
    """The trial to draw: the first that did not survive, else the first."""
    drawn = [t for t in s.trials if "timeline" in (t.details or {})]
    for t in drawn:
        if t.outcome != TrialOutcome.SURVIVED:
            return t
    return drawn[0] if drawn else None


def timeline_svg(tl: dict, faults: list[dict], width: int = 640) -> str:
    """One row a fault on top (a bar from its start to its end, labelled),
    then a strip per topic (messages per second, bin by bin) and a strip
    per node whose memory the container reported (MiB in use, sample by
    sample), on the same time axis, the faults shaded across the strips."""
    bin_ms = tl["bin_ms"]
    topics = tl["topics"]
    memory = tl.get("memory_mib", {})
    n_bins = max((len(c) for c in topics.values()), default=1)
    span_ms = n_bins * bin_ms
    left, right, strip_h, gap, row_h = 150.0, 12.0, 34.0, 8.0, 15.0
    plot_w = width - left - right
    top = 6.0 + len(faults) * row_h + 4.0
    bottom = top + (len(topics) + len(memory)) * (strip_h + gap)
    height = int(bottom + 22)

    def x(ms: float) -> float:
        return left + max(0.0, min(1.0, ms / span_ms)) * plot_w

    title = f"timeline: {', '.join(topics)} over {span_ms / 1000:.1f} s, {len(faults)} fault(s)"
    out = [
        f'<svg class="chart" xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" role="img" aria-label="{e(title)}"><title>{e(title)}</title>'
    ]
    shades = []  # drawn over the strips
    for i, f in enumerate(faults):
        start, end, node, what = f["from_ms"], f["to_ms"], f["node"], f["what"]
        x0, x1 = x(start), x(end)
        w = max(2.0, x1 - x0)
        y = 6.0 + i * row_h
        label = f"{what} → {node}"
        tip = f"<title>{e(label)} at {start:.0f}–{end:.0f} ms</title>"
        shades.append(f'<rect x="{x0:.1f}" y="{top:.1f}" width="{w:.1f}" height="{bottom - top - gap:.1f}" '
                      f'fill="#d13b3b" fill-opacity="{0.15 if w > 2 else 0.6}">{tip}</rect>')  # fmt: skip
        out.append(f'<rect x="{x0:.1f}" y="{y:.1f}" width="{w:.1f}" height="{row_h - 4}" fill="#d13b3b">{tip}</rect>')
        at_end = x0 > left + 0.6 * plot_w
        tx, anchor = (x0 - 4, "end") if at_end else (x0 + w + 4, "start")
        out.append(f'<text x="{tx:.1f}" y="{y + row_h - 5:.1f}" text-anchor="{anchor}" class="tick">{e(label)}</text>')
    strips = [(name, [((j + 0.5) * bin_ms, c * 1000.0 / bin_ms) for j, c in enumerate(counts)], "Hz")
              for name, counts in topics.items()]  # fmt: skip
    strips += [(f"{node} memory", points, "MiB") for node, points in memory.items()]
    for i, (name, points, unit) in enumerate(strips):
        color = TOPIC_COLORS[i % len(TOPIC_COLORS)]
        out.extend(_strip(name, points, unit, (top + i * (strip_h + gap), strip_h), x, color, marks=unit == "MiB"))
    out.extend(shades)
    axis = bottom - gap + 4
    step_s = max(1, round(span_ms / 1000 / 8))
    t_s = 0
    while t_s * 1000 <= span_ms:
        tx = x(t_s * 1000)
        out.append(f'<line x1="{tx:.1f}" y1="{axis}" x2="{tx:.1f}" y2="{axis + 4}" class="axis"/>')
        out.append(f'<text x="{tx:.1f}" y="{axis + 15}" text-anchor="middle" class="tick">{t_s} s</text>')
        t_s += step_s
    out.append(f'<line x1="{left}" y1="{axis}" x2="{left + plot_w:.1f}" y2="{axis}" class="axis"/></svg>')
    return "".join(out)


def _strip(
    name: str,
    points: Sequence[Sequence[float]],
    unit: str,
    box: tuple[float, float],
    x: Callable[[float], float],
    color: str,
    marks: bool = False,
) -> list[str]:
    """One strip of the timeline, ``box`` (top, height) high, across the
    time axis ``x`` (ms to a position, clamped to the plot): ``points``
    (ms, value) as a line from 0 at its foot to the peak at its top,
    labelled with ``name`` and the peak in ``unit``; with ``marks``, a dot
    a point."""
    y0, height = box
    peak = max((v for _, v in points), default=0.0) or 1.0
    xy = [(x(ms), y0 + height - (v / peak) * height) for ms, v in points]
    left, right = x(0.0), x(math.inf)
    out = [
        f'<rect x="{left}" y="{y0}" width="{right - left:.1f}" height="{height}" class="band"/>',
        f'<polyline points="{" ".join(f"{px:.1f},{py:.1f}" for px, py in xy)}" fill="none" stroke="{color}" '
        'stroke-width="1.6"/>',
        f'<text x="{left - 6}" y="{y0 + height / 2 + 4:.1f}" text-anchor="end" class="tick">{e(name)}</text>',
        f'<text x="{left - 6}" y="{y0 + 9:.1f}" text-anchor="end" class="tick">{peak:.{1 if peak < 10 else 0}f} '
        f"{unit}</text>",
    ]
    if marks:  # samples seconds apart: each shown, a lone one too
        out += [f'<circle cx="{px:.1f}" cy="{py:.1f}" r="2.2" fill="{color}"/>' for px, py in xy]
    return out


def timeline(s: Scenario) -> str:
    t = _timeline_trial(s)
    if t is None:
        return ""
    return (
        f"<h4>Timeline of trial {e(t.index)} ({e(t.outcome)})</h4>"
        "<p class=\"muted small\">Each watched topic's messages per second, in 100 ms bins, from the trial's "
        "start, and each node's memory in use as its container reported it (isolated mode: once a second, "
        "or every diagnostic_updater.period; "
        "from its last report before the trial; a node with no report in that time has no strip); "
        "the faults shaded.</p>" + timeline_svg(t.details["timeline"], t.details.get("faults", []))
    )


def _event_words(ev: dict) -> str:
    """One of the container's events of a trial: what, of which node and
    process (a REPAIRED's: the node whose death left what was repaired),
    when, and what it says. A node or pid not known is left out."""
    who = ev.get("node") or ""
    if ev.get("pid"):
        who = f"{who} (pid {ev['pid']})".strip()
    if ev["event"] == "REPAIRED":
        what = " ".join(filter(None, [ev.get("repaired"), who and f"left by {who}"]))
    else:
        what = who
    said = ev.get("what", "")
    return " ".join(filter(None, [ev["event"], what, f"at {ev['at_ms']:.0f} ms"])) + (f": {said}" if said else "")


def trial_facts(t: Trial) -> str:
    """A trial's details as words (any trial's, the rig's too): its cause
    first, then its faults, what each topic did, and anything else
    recorded (the timeline is drawn, not listed)."""
    d = dict(t.details or {})
    parts = []
    why = d.pop("why", None)
    if why:
        parts.append(f"<b>{e(why)}</b>")
    faults = d.pop("faults", None)
    if faults:
        parts.append("faults: " + e("; ".join(f"{f['what']} → {f['node']} at {f['from_ms']:.0f} ms" for f in faults)))
    for ev in d.pop("events", None) or []:
        parts.append(e(_event_words(ev)))
    topics = d.pop("topics", None) or {}
    for name, f in topics.items():
        parts.append(f"{e(name)} {f['rate_hz']:.1f} Hz, longest gap {f['longest_gap_s']:.3f} s")
    d.pop("timeline", None)
    reports = d.pop("crash_reports", None) or {}
    log = d.pop("container_log", None)
    for k, v in sorted(d.items()):
        parts.append(f"{e(k)}: {e(v if isinstance(v, str) else json.dumps(v, sort_keys=True))}")
    text = "<br>".join(parts)
    for who, report in reports.items():
        text += f"<details><summary>crash report of {e(who)}</summary><pre>{e(report)}</pre></details>"
    if log:
        text += f"<details><summary>container log (last lines)</summary><pre>{e(log)}</pre></details>"
    return text
