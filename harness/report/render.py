"""report.html: one self-contained page (inline CSS and SVG, no scripts)."""

from __future__ import annotations

import json
import re
from datetime import datetime
from html import escape
from pathlib import Path

from . import charts, stats, system_view
from .model import CONTAINER_DEATH, REPORT_HTML, TRIAL_OUTCOMES, Report, Scenario, TrialOutcome, write_atomic
from .stats import Proportion

#: Without an expectation, a cell is amber from this survival rate up to
#: (not including) 100%, and red below it.
AMBER_FROM = 0.8

STATUS_TEXT = {
    "green": "ok",
    "amber": "some trials did not survive",
    "red": "failed",
    "grey": "no trials",
}


def e(value: object) -> str:
    """Escaped text for HTML content and attribute values."""
    return escape("" if value is None else str(value), quote=True)


def pct(rate: float | None) -> str:
    return stats.percent(rate)


def ci_text(p: Proportion) -> str:
    if not p.trials:
        return "no trials"
    return f"{p.low * 100:.1f}–{p.high * 100:.1f}%"


def scenario_status(s: Scenario) -> tuple[str, str]:
    """The colour of a scenario and why: red when pytest failed it or an
    expectation was not met; grey without trials; green when it had
    expectations and met them all; otherwise by survival rate (100% green,
    from AMBER_FROM amber, below red)."""
    if s.outcome in ("failed", "error"):
        return "red", f"test {s.outcome}"
    unmet = [x for x in s.expectations if x.met is False]
    if unmet:
        return "red", f"{len(unmet)} expectation(s) not met"
    if not s.trials:
        return "grey", "no trials" + (f" (test {s.outcome})" if s.outcome else "")
    if s.expectations:
        return "green", "expectations met"
    rate = s.survival().rate or 0.0
    if rate >= 1.0:
        return "green", "every trial survived"
    if rate >= AMBER_FROM:
        return "amber", f"survival {pct(rate)}, no expectation set"
    return "red", f"survival {pct(rate)}, no expectation set"


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "-", text).strip("-")[:80] or "scenario"


def anchors(report: Report) -> dict[int, str]:
    """A unique HTML id per scenario (by position in the report)."""
    seen: set[str] = set()
    out = {}
    for i, s in enumerate(report.scenarios):
        base = "s-" + _slug(s.nodeid)
        anchor, n = base, 2
        while anchor in seen:
            anchor, n = f"{base}-{n}", n + 1
        seen.add(anchor)
        out[i] = anchor
    return out


def _fmt_time(iso: str | None) -> str:
    if not iso:
        return "–"
    try:
        return datetime.fromisoformat(iso.replace("Z", "+00:00")).strftime("%Y-%m-%d %H:%M:%S UTC")
    except ValueError:
        return iso


def _fmt_duration(seconds: float | None) -> str:
    if seconds is None:
        return "–"
    if seconds < 1:
        return f"{seconds * 1000:.0f} ms"
    if seconds < 60:
        return f"{seconds:.1f} s"
    minutes, sec = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h {minutes:02d}m {sec:02d}s" if hours else f"{minutes}m {sec:02d}s"


def _mitigations(m: dict) -> str:
    if not m:
        return "none"
    parts = []
    for k, v in m.items():
        if v is True:
            parts.append(f"{k}")
        elif v is False:
            parts.append(f"no {k}")
        else:
            parts.append(f"{k}={v}")
    return ", ".join(parts)


CSS = """
:root{--green:#dff3e4;--green-fg:#17692f;--amber:#fff0c2;--amber-fg:#7a5600;--red:#fbdcdc;--red-fg:#9d1c1c;
--grey:#eeeeee;--grey-fg:#555;--line:#d8d8d8;--muted:#666;--accent:#1d5fa8}
*{box-sizing:border-box}
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;color:#1b1b1b;
margin:0 auto;max-width:1180px;padding:20px 24px 60px;background:#fff}
h1{font-size:22px;margin:0 0 4px} h2{font-size:18px;margin:32px 0 10px;border-bottom:2px solid #333;padding-bottom:4px}
h3{font-size:16px;margin:0} h4{font-size:14px;margin:12px 0 4px}
code,pre,.mono{font-family:ui-monospace,SFMono-Regular,Menlo,Consolas,monospace;font-size:12.5px}
pre{background:#f6f6f6;border:1px solid var(--line);padding:8px 10px;overflow:auto;max-height:480px;white-space:pre}
a{color:var(--accent);text-decoration:none} a:hover{text-decoration:underline}
.muted{color:var(--muted)} .small{font-size:12px}
.totals{display:flex;flex-wrap:wrap;gap:8px;margin:10px 0}
.badge{display:inline-block;padding:2px 9px;border-radius:11px;font-weight:600;font-size:12.5px;background:var(--grey);color:var(--grey-fg)}
.b-passed,.b-green{background:var(--green);color:var(--green-fg)} .b-failed,.b-error,.b-red{background:var(--red);color:var(--red-fg)}
.b-skipped,.b-grey{background:var(--grey);color:var(--grey-fg)} .b-amber{background:var(--amber);color:var(--amber-fg)}
table{border-collapse:collapse} th,td{text-align:left;vertical-align:top;padding:4px 10px 4px 0}
table.meta th{font-weight:600;color:var(--muted);padding-right:14px;white-space:nowrap}
table.grid{width:100%} table.grid th,table.grid td{border:1px solid var(--line);padding:6px 8px}
table.grid thead th{background:#f3f3f3}
table.matrix th.row{background:#f8f8f8;white-space:nowrap}
td.cell{padding:0} .entry{display:block;padding:6px 8px;color:inherit;border-top:1px solid #fff}
.entry:first-child{border-top:0} .entry:hover{text-decoration:none;filter:brightness(0.96)}
.entry .big{font-size:15px;font-weight:700} .entry .sub{font-size:12px}
.st-green{background:var(--green);color:var(--green-fg)} .st-amber{background:var(--amber);color:var(--amber-fg)}
.st-red{background:var(--red);color:var(--red-fg)} .st-grey{background:var(--grey);color:var(--grey-fg)}
td.empty{background:repeating-linear-gradient(45deg,#fafafa,#fafafa 6px,#f1f1f1 6px,#f1f1f1 12px)}
.legend span{display:inline-block;margin-right:14px} .legend i{display:inline-block;width:12px;height:12px;border-radius:2px;vertical-align:-1px;margin-right:4px}
article.scenario{border:1px solid var(--line);border-left-width:6px;border-radius:4px;padding:12px 16px;margin:16px 0}
article.st-green{border-left-color:#2e9d4f;background:#fff;color:inherit} article.st-amber{border-left-color:#e0a100;background:#fff;color:inherit}
article.st-red{border-left-color:#d13b3b;background:#fff;color:inherit} article.st-grey{border-left-color:#aaa;background:#fff;color:inherit}
.head{display:flex;justify-content:space-between;align-items:baseline;gap:12px;flex-wrap:wrap}
blockquote.claim{margin:8px 0;padding:6px 12px;border-left:3px solid #bbb;background:#fafafa;font-style:italic}
.chips span{display:inline-block;background:#eef2f7;border-radius:3px;padding:1px 7px;margin:0 6px 3px 0;font-size:12.5px}
.cols{display:flex;flex-wrap:wrap;gap:28px}
.ok{color:var(--green-fg);font-weight:600} .no{color:var(--red-fg);font-weight:600}
.hang{border:1px solid #efd48a;background:#fffaf0;border-radius:4px;padding:8px 12px;margin:8px 0}
details>summary{cursor:pointer;color:var(--accent);margin:4px 0}
svg.chart{display:block;max-width:100%;height:auto;margin:2px 0 10px}
svg.chart .band{fill:#fbfbfb;stroke:#e4e4e4} svg.chart .grid{stroke:#ececec}
svg.chart .axis{stroke:#777} svg.chart .tick{font-size:11px;fill:#555}
svg.chart .axis-title{font-size:11.5px;fill:#333} svg.chart .whisker{stroke:#8a8a8a}
svg.chart .box{fill:#d7e6f7;stroke:#7aa4d1} svg.chart .dot{fill:#1d5fa8;fill-opacity:.55}
svg.chart .median{stroke:#c0392b;stroke-width:2.5} svg.chart .median-label{font-size:11.5px;fill:#c0392b;font-weight:600}
svg.bar{vertical-align:middle;border-radius:2px}
td.num,th.num{text-align:right}
.death{color:#b3261e}
footer{margin-top:40px;color:var(--muted);font-size:12px}
@media print{details{display:block} pre{max-height:none}}
"""


def _header(report: Report) -> str:
    run = report.run
    summary = report.summary()
    host = run.host or {}
    git = run.git or {}
    badges = []
    deaths = report.container_deaths()
    if deaths.trials:
        cls = "b-red" if deaths.successes else "b-green"
        badges.append(
            f'<span class="badge {cls}">{deaths.successes} container death'
            f"{'' if deaths.successes == 1 else 's'} in {deaths.trials} isolated trials "
            f"(95% upper bound {e(pct(deaths.high))})</span>"
        )
    for outcome, n in summary["outcomes"].items():
        if n or outcome in ("passed", "failed"):
            # "0 failed" says so in the plain colour, not in red.
            cls = f"b-{outcome}" if n else ""
            badges.append(f'<span class="badge {e(cls)}">{n} {e(outcome)}</span>')
    t = summary["trial_outcomes"]
    trial_text = ", ".join(f"{n} {k}" for k, n in t.items() if n) or "none"
    exp = summary["expectations"]
    badges.append(f'<span class="badge">{summary["trials"]} trials: {e(trial_text)}</span>')
    badges.append(
        f'<span class="badge">{summary["hangs"]} hang diagnos{"is" if summary["hangs"] == 1 else "es"}</span>'
    )
    if exp["met"] or exp["not_met"]:
        cls = "b-red" if exp["not_met"] else "b-green"
        badges.append(f'<span class="badge {cls}">expectations met: {exp["met"]}/{exp["met"] + exp["not_met"]}</span>')
    if exp.get("deferred"):
        badges.append(
            f'<span class="badge b-amber">{exp["deferred"]} expectation(s) judged only '
            f"when shards are merged (shard {e(run.shard or '?')})</span>"
        )
    if run.workers:
        badges.append(f'<span class="badge">run by {run.workers} pytest-xdist workers</span>')
    if run.shards:
        parts = ", ".join(
            f"{sh.get('shard') or 'unsharded'} ({sh.get('host') or '?'}, {(sh.get('commit') or '?')[:12]})"
            for sh in run.shards
        )
        badges.append(f'<span class="badge">merged from {len(run.shards)} run(s): {e(parts)}</span>')

    commit = git.get("commit")
    commit_text = "–"
    if commit:
        commit_text = f"<code>{e(commit[:12])}</code>"
        if git.get("branch"):
            commit_text += f" on <code>{e(git['branch'])}</code>"
        if git.get("dirty"):
            commit_text += ' <span class="badge b-amber">dirty</span>'
    cpu = host.get("cpu_model") or "unknown CPU"
    cpu_line = f"{e(cpu)} × {e(host.get('cpu_count', '?'))}"
    if host.get("cpu_usable") and host.get("cpu_usable") != host.get("cpu_count"):
        cpu_line += f" ({e(host['cpu_usable'])} usable)"
    cpu_line += (
        "; PKU yes (on jemalloc, the isolated default, unless --no-pkeys, each live node process writes its heap "
        "under a key of its own, up to 14; "
        "past 14, nodes share keys and are not protected from those they share with; the 15th key is the "
        "container's own, over its allocator tables)"
        if host.get("pku")
        else "; PKU no"
    )
    rows = [
        (
            "started",
            f'{e(_fmt_time(run.started))} <span class="muted">(took {e(_fmt_duration(run.duration_s))}, '
            f"pytest exit status {e(run.exit_status)})</span>",
        ),
        (
            "host",
            f"{e(host.get('hostname', '?'))}: Linux {e(host.get('kernel', '?'))} {e(host.get('machine', ''))}, "
            f"{e(host.get('glibc') or 'libc ?')}",
        ),
        ("cpu", cpu_line),
        ("project", e(run.project or "–")),
        ("commit", commit_text),
        ("python", e(run.python or "–")),
        ("packages", e(", ".join(f"{k} {v}" for k, v in run.packages.items()) or "–")),
        ("pytest", f"<code>{e(' '.join(run.pytest_args) or '(no arguments)')}</code>"),
        (
            "container",
            f"<code>{e(run.container_exe)}</code>" if run.container_exe else "cloneguard's component_container",
        ),
        ("deep mode", "on" if run.deep else "off"),
    ]
    if run.junit:
        rows.append(("junit", f'<a href="{e(run.junit)}">{e(run.junit)}</a>'))
    meta = "".join(f"<tr><th>{e(k)}</th><td>{v}</td></tr>" for k, v in rows)
    label = f'<p class="muted">{e(run.label)}</p>' if run.label else ""
    return (
        f'<header><h1>Crash-resilience report <span class="mono">{e(run.id)}</span></h1>{label}'
        f'<div class="totals">{"".join(badges)}</div><table class="meta">{meta}</table></header>'
    )


def _legend() -> str:
    items = [
        ("green", "expectations met, or every trial survived"),
        ("amber", f"no expectation and survival {AMBER_FROM:.0%}–<100%"),
        ("red", f"test failed, an expectation not met, or survival <{AMBER_FROM:.0%} without one"),
        ("grey", "no trials"),
    ]
    return '<p class="legend small">' + "".join(f'<span><i class="st-{c}"></i>{e(t)}</span>' for c, t in items) + "</p>"


def _matrix(report: Report, ids: dict[int, str]) -> str:
    faults: list[str | None] = []
    profiles: list[str | None] = []
    cells: dict[tuple, list[int]] = {}
    described = [i for i, s in enumerate(report.scenarios) if s.fault is not None or s.profile is not None]
    others = [i for i in range(len(report.scenarios)) if i not in described]
    if not described:  # nothing called describe(): one row, one column
        described, others = others, []
    for i in described:
        s = report.scenarios[i]
        if s.fault not in faults:
            faults.append(s.fault)
        if s.profile not in profiles:
            profiles.append(s.profile)
        cells.setdefault((s.fault, s.profile), []).append(i)
    if not report.scenarios:
        return "<p>No scenarios ran.</p>"

    def label(v: str | None, what: str) -> str:
        return e(v) if v is not None else f'<span class="muted">(no {what})</span>'

    head = "".join(f"<th>{label(p, 'profile')}</th>" for p in profiles)
    rows = []
    for fault in faults:
        tds = []
        for profile in profiles:
            members = cells.get((fault, profile))
            if not members:
                tds.append('<td class="empty"></td>')
                continue
            entries = []
            distinguish = len(members) > 1
            for i in members:
                entries.append(_matrix_entry(report.scenarios[i], ids[i], distinguish))
            tds.append(f'<td class="cell">{"".join(entries)}</td>')
        rows.append(f'<tr><th class="row">{label(fault, "fault")}</th>{"".join(tds)}</tr>')
    rest = ""
    if others:
        links = ", ".join(
            f'<a href="#{e(ids[i])}" class="st-{scenario_status(report.scenarios[i])[0]}" style="padding:0 4px">'
            f"{e(report.scenarios[i].name)}</a>"
            for i in others
        )
        rest = f'<p class="small">Tests without a fault or profile: {links}</p>'
    return (
        f'<table class="grid matrix"><thead><tr><th>fault \\ profile</th>{head}</tr></thead>'
        f"<tbody>{''.join(rows)}</tbody></table>{rest}{_legend()}"
    )


def _matrix_entry(s: Scenario, anchor: str, distinguish: bool) -> str:
    status, why = scenario_status(s)
    p = s.survival()
    lines = []
    if distinguish:
        lines.append(
            f'<div class="sub"><b>{e(s.name)}</b>'
            f"{' · ' + e(_mitigations(s.mitigations)) if s.mitigations else ''}</div>"
        )
    deaths = s.counts().get(CONTAINER_DEATH, 0)
    if deaths and s.isolated:
        lines.append(f'<div class="big death">{deaths} container death{"" if deaths == 1 else "s"}</div>')
    if p.trials:
        lines.append(f'<div class="big">{p.successes}/{p.trials} survived</div>')
        lines.append(f'<div class="sub">{e(pct(p.rate))} (95% CI {e(ci_text(p))})</div>')
    else:
        lines.append(f'<div class="big">no trials</div><div class="sub">test {e(s.outcome or "did not finish")}</div>')
    for x in s.expectations:
        mark = {True: "✓", False: "✗", None: "(judged at merge)"}[x.met]
        lines.append(f'<div class="sub">expect {e(x.outcome)} {e(x.requirement())} {mark}</div>')
    if s.hangs:
        lines.append(f'<div class="sub">{len(s.hangs)} hang{"s" if len(s.hangs) > 1 else ""} diagnosed</div>')
    if s.outcome in ("failed", "error") and not any(x.met is False for x in s.expectations):
        lines.append(f'<div class="sub">test {e(s.outcome)}</div>')
    title = f"{s.name}: {why}" + (f" — {s.claim}" if s.claim else "")
    return f'<a class="entry st-{status}" href="#{e(anchor)}" title="{e(title)}">{"".join(lines)}</a>'


def _counts_table(s: Scenario) -> str:
    counts = s.counts()
    total = len(s.trials)
    rows = []
    for outcome in list(TRIAL_OUTCOMES) + [k for k in counts if k not in TRIAL_OUTCOMES]:
        n = counts.get(outcome, 0)
        share = f"{n / total * 100:.1f}%" if total else "–"
        color = charts.OUTCOME_COLORS.get(outcome, "#999")
        rows.append(
            f'<tr><td><i style="display:inline-block;width:10px;height:10px;background:{color};'
            f'margin-right:6px"></i>{e(outcome)}</td><td class="num">{n}</td><td class="num">{share}</td></tr>'
        )
    return f'<table class="counts">{"".join(rows)}</table>'


def _expectations(s: Scenario) -> str:
    if not s.expectations:
        return '<p class="muted">No expectation recorded.</p>'
    rows = []
    for x in s.expectations:
        verdict = {
            True: '<span class="ok">✓ met</span>',
            False: '<span class="no">✗ not met</span>',
            None: '<span class="muted">judged when the shards are merged</span>',
        }[x.met]
        ci = f"{x.ci_low * 100:.1f}–{x.ci_high * 100:.1f}%" if x.trials else "–"
        rows.append(
            f"<tr><td>{e(x.outcome)}</td><td>{e(x.requirement())}</td>"
            f'<td class="num">{e(pct(x.rate))} ({x.successes}/{x.trials})</td><td>{e(ci)}</td><td>{verdict}</td></tr>'
        )
    return (
        '<table class="grid"><thead><tr><th>outcome</th><th>promised rate</th><th class="num">measured</th>'
        f"<th>95% CI</th><th></th></tr></thead><tbody>{''.join(rows)}</tbody></table>"
    )


def _latency(s: Scenario) -> str:
    series = s.latency_series()
    if not series:
        return ""
    summaries = s.latency_summaries()
    head = "".join(f'<th class="num">{h}</th>' for h in ("n", "min", "median", "p90", "p99", "max", "mean"))
    rows = []
    for name, summ in summaries.items():
        cells = [str(summ.n)] + [
            charts.fmt_ms(getattr(summ, k)) for k in ("min", "median", "p90", "p99", "max", "mean")
        ]
        rows.append(
            f"<tr><td><code>{e(name)}</code></td><td>{e(s.unit(name))}</td>"
            + "".join(f'<td class="num">{e(c)}</td>' for c in cells)
            + "</tr>"
        )
    plots = "".join(charts.latency_strip(name, values, s.unit(name)) for name, values in series.items() if values)
    title = "Latency (ms)" if not s.units else "Measurements"
    return (
        f'<h4>{title}</h4><table class="grid"><thead><tr><th>series</th><th>unit</th>{head}</tr></thead>'
        f"<tbody>{''.join(rows)}</tbody></table>{plots}"
    )


def _hang_anchor(anchor: str, trial: int | None) -> str:
    return f"{anchor}-hang-{trial}"


def _hangs(s: Scenario, anchor: str) -> str:
    if not s.hangs:
        return ""
    hung = s.counts().get(TrialOutcome.HUNG, 0)
    out = [f"<h4>Hangs ({len(s.hangs)} diagnosed, {hung} trial{'s' if hung != 1 else ''} hung)</h4>"]
    seen = set()
    for h in s.hangs:
        where = f"trial {e(h.trial)}" if h.trial is not None else "hang"
        facts = []
        if h.lock is not None:
            facts.append(f"lock <code>{e(h.lock)}</code>")
        if h.owner_tid is not None:
            facts.append(f"owner tid <code>{e(h.owner_tid)}</code>")
        if h.owner_node is not None:
            facts.append(f"owner node <code>{e(h.owner_node)}</code>")
        for k, v in (h.details or {}).items():
            facts.append(f"{e(k)} <code>{e(v if isinstance(v, str) else json.dumps(v))}</code>")
        fact_line = f'<div class="small">{" · ".join(facts)}</div>' if facts else ""
        stacks = ""
        if h.stacks:
            n_lines = h.stacks.count("\n") + 1
            stacks = f"<details><summary>stacks ({n_lines} lines)</summary><pre>{e(h.stacks)}</pre></details>"
        id_attr = ""
        if h.trial is not None and h.trial not in seen:
            seen.add(h.trial)
            id_attr = f' id="{e(_hang_anchor(anchor, h.trial))}"'
        out.append(f'<div class="hang"{id_attr}><b>{where}:</b> {e(h.summary)}{fact_line}{stacks}</div>')
    return "".join(out)


def _trials_table(s: Scenario, anchor: str) -> str:
    if not s.trials:
        return ""
    diagnosed = {h.trial for h in s.hangs if h.trial is not None}
    series = list(s.latency_series())
    head = "".join(f'<th class="num">{e(n)} {e(s.unit(n))}</th>' for n in series)
    rows = []
    for t in s.trials:
        lat = []
        for name in series:
            vals = t.latency_values(name)
            lat.append(f'<td class="num">{e(", ".join(charts.fmt_ms(v) for v in vals) or "–")}</td>')
        details = system_view.trial_facts(t)
        color = charts.OUTCOME_COLORS.get(t.outcome, "#999")
        outcome = e(t.outcome)
        if t.index in diagnosed:
            outcome = f'<a href="#{e(_hang_anchor(anchor, t.index))}">{outcome} (diagnosis)</a>'
        rows.append(
            f'<tr><td class="num">{e(t.index)}</td><td style="color:{color};font-weight:600">{outcome}</td>'
            f'<td class="mono">{e(t.seed if t.seed is not None else "–")}</td>{"".join(lat)}'
            f'<td class="mono small">{details}</td></tr>'
        )
    return (
        f"<details><summary>all {len(s.trials)} trials</summary>"
        f'<table class="grid small"><thead><tr><th class="num">#</th><th>outcome</th><th>seed</th>{head}'
        f"<th>details</th></tr></thead><tbody>{''.join(rows)}</tbody></table></details>"
    )


def _scenario(s: Scenario, anchor: str) -> str:
    status, why = scenario_status(s)
    p = s.survival()
    chips = [
        f"<span>fault: <b>{e(s.fault or '–')}</b></span>",
        f"<span>profile: <b>{e(s.profile or '–')}</b></span>",
        f"<span>mitigations: <b>{e(_mitigations(s.mitigations))}</b></span>",
    ]
    outcome = s.outcome or "did not finish"
    parts = [
        f'<article class="scenario st-{status}" id="{e(anchor)}">',
        f'<div class="head"><h3>{e(s.name)}</h3><span><span class="badge b-{e(outcome)}">{e(outcome)}</span> '
        f'<span class="badge b-{status}">{e(why)}</span> <span class="muted small">{e(_fmt_duration(s.duration_s))}</span></span></div>',
        f'<div class="muted small mono">{e(s.nodeid)}</div>',
        f'<div class="chips">{"".join(chips)}</div>',
    ]
    if s.claim:
        parts.append(f'<blockquote class="claim">Claim: {e(s.claim)}</blockquote>')
    if s.message:
        parts.append(
            f'<p><b>{e(outcome)}:</b> <span class="mono" style="white-space:pre-wrap">{e(s.message)}</span></p>'
        )
    if s.longrepr:
        parts.append(f"<details><summary>pytest output</summary><pre>{e(s.longrepr)}</pre></details>")
    if p.trials:
        survival = (
            f"<p><b>{p.successes}/{p.trials} survived</b> — {e(pct(p.rate))} "
            f'<span class="muted">(95% Wilson CI {e(ci_text(p))})</span></p>'
            f"{charts.outcome_bar(s.counts())}{_counts_table(s)}"
        )
    else:
        survival = '<p class="muted">No trials recorded.</p>'
    parts.append(
        f'<div class="cols"><div><h4>Trials</h4>{survival}</div>'
        f"<div><h4>Expectations</h4>{_expectations(s)}</div></div>"
    )
    if s.notes:
        parts.append("<h4>Notes</h4><ul>" + "".join(f"<li>{e(n)}</li>" for n in s.notes) + "</ul>")
    if system_view.has_system_view(s):
        parts.append(system_view.nodes_table(s))
        parts.append(system_view.topics_table(s))
        parts.append(system_view.timeline(s))
    parts.append(_latency(s))
    parts.append(_hangs(s, anchor))
    parts.append(_trials_table(s, anchor))
    parts.append('<p class="small"><a href="#matrix">↑ back to the matrix</a></p></article>')
    return "".join(parts)


def render_html(report: Report) -> str:
    ids = anchors(report)
    body = [
        _header(report),
        '<h2 id="matrix">Fault × profile</h2>',
        '<p class="muted small">Survived/total trials, survival rate with its 95% Wilson interval, and the '
        "promised rate if the scenario set one. Click a cell for the scenario.</p>",
        _matrix(report, ids),
        '<h2 id="scenarios">Scenarios</h2>',
        "".join(_scenario(s, ids[i]) for i, s in enumerate(report.scenarios)) or "<p>No scenarios ran.</p>",
        f'<footer>cloneguard crash-resilience report · run <span class="mono">{e(report.run.id)}</span> · '
        "data in report.json · re-render with <code>python -m cloneguard.harness render</code></footer>",
    ]
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>cloneguard report {e(report.run.id)}</title><style>{CSS}</style></head>"
        f"<body>{''.join(body)}</body></html>\n"
    )


def write_html(report: Report, path: str | Path | None = None) -> Path:
    if path is None:
        if report.directory is None:
            raise ValueError("no path given and the report has no directory")
        path = Path(report.directory) / REPORT_HTML
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, render_html(report))
    return path
