"""A report as a Markdown summary: the run, its container deaths, a table of
every scenario's trials (container deaths, survived, rate, 95% interval,
expectation) and every trial that did not survive with its diagnosis
(container deaths first), for docs and closing notes.

    python -m cloneguard.harness summary reports/deep [--hang-chars 240]
"""

from __future__ import annotations

import re

from . import stats
from .model import CONTAINER_DEATH, Report, Scenario, TrialOutcome

#: more non-survivals than this in one scenario are grouped by cause
GROUP_OVER = 5


def _pct(x: float | None) -> str:
    return stats.percent(x, none="-")


def _expectation(s: Scenario) -> str:
    parts = []
    for e in s.expectations:
        bound = f"≥ {_pct(e.at_least)}" if e.at_least is not None else f"≤ {_pct(e.at_most)}"
        verdict = {True: "met", False: "missed", None: "not judged"}[e.met]
        parts.append(f"{e.outcome} {bound}: {verdict}")
    return "; ".join(parts) or "(measured, not promised)"


def _cell(s: Scenario) -> str:
    return s.name.removeprefix("test_")


def _others(counts: dict[str, int]) -> str:
    return (
        ", ".join(
            f"{n} {k}" for k, n in sorted(counts.items()) if k not in (TrialOutcome.SURVIVED, CONTAINER_DEATH) and n
        )
        or "-"
    )


def _cause(text: str) -> str:
    """A diagnosis or reason with its numbers, addresses and node names
    taken out, so that hangs of one cause read the same."""
    first = text.split("; ")[0]
    return re.sub(r"0x[0-9a-f]+|/[a-z_]+\d+|\d+", "#", first)


def markdown(report: Report, *, hang_chars: int = 240) -> str:
    run = report.run
    git = run.git or {}
    commit = (git.get("commit") or "?")[:12] + (" (dirty tree)" if git.get("dirty") else "")
    host = run.host or {}
    lines = [
        f"Run `{run.id}` at commit `{commit}`, {run.duration_s or 0:.0f} s"
        + (f" on {run.workers} workers" if run.workers else "")
        + (f", {len(run.shards)} shards merged" if run.shards else "")
        + (
            f"; host: {host.get('cpu_count', '?')} CPUs, kernel {host.get('kernel', '?')}, "
            f"{host.get('glibc', 'glibc ?')}"
            if host
            else ""
        ),
        "",
        f"    python -m pytest {' '.join(run.pytest_args)}",
        "",
    ]
    deaths = report.container_deaths()
    if deaths.trials:
        lines += [
            f"Container deaths (every node at once) in the isolated cells: **{deaths.successes}** in "
            f"{deaths.trials} trials (95% upper bound {_pct(deaths.high)}).",
            "",
        ]
    lines += [
        "| scenario | profile | trials | container deaths | survived | rate | 95% interval | other outcomes "
        "| expectation |",
        "|---|---|---:|---:|---:|---:|---|---|---|",
    ]
    for s in sorted(report.scenarios, key=lambda s: (s.fault or "", s.nodeid)):
        if not s.trials:
            continue
        p = s.survival()
        counts = s.counts()
        lines.append(
            f"| {_cell(s)} | {s.profile or '-'} | {p.trials} | {counts.get(CONTAINER_DEATH, 0)} | {p.successes} "
            f"| {_pct(p.rate)} | {_pct(p.low)}–{_pct(p.high)} | {_others(counts)} | {_expectation(s)} |"
        )
    troubled = [s for s in report.scenarios if any(not t.survived for t in s.trials)]
    if troubled:
        lines += [
            "",
            "Every trial that did not survive (thread-mode baselines, whose trials are",
            "expected to crash, are left out when all of them did):",
            "",
        ]
    # Cells with container deaths first, and in each its container deaths first.
    for s in sorted(troubled, key=lambda s: (not (s.isolated and s.counts().get(CONTAINER_DEATH)), s.nodeid)):
        bad = sorted((t for t in s.trials if not t.survived), key=lambda t: (t.outcome != CONTAINER_DEATH, t.index))
        if not s.isolated and all(t.outcome == CONTAINER_DEATH for t in bad):
            continue
        hangs = {h.trial: h for h in s.hangs}
        lines.append(f"- **{_cell(s)}** ({s.profile}): {len(bad)} of {len(s.trials)}")
        groups: dict[str, list] = {}
        for t in bad:
            why = str(t.details.get("why", "")).strip()
            diagnosis = hangs[t.index].summary if t.index in hangs else ""
            key = _cause(diagnosis or why) if len(bad) > GROUP_OVER else str(t.index)
            groups.setdefault(key, []).append((t, why, diagnosis))
        for members in sorted(groups.values(), key=lambda m: (m[0][0].outcome != CONTAINER_DEATH, -len(m))):
            t, why, diagnosis = members[0]
            what = "a container death" if t.outcome == CONTAINER_DEATH else t.outcome
            text = (
                f"  - trial {t.index} (seed {t.seed}), {what}"
                if len(members) == 1
                else f"  - {len(members)} trials ({', '.join(str(m[0].index) for m in members[:12])}"
                f"{' …' if len(members) > 12 else ''}), {what} alike; the first"
            )
            text += f": {why}" if why else ""
            if diagnosis:
                cut = diagnosis if len(diagnosis) <= hang_chars else diagnosis[:hang_chars] + " …"
                text += f". Diagnosis: {cut}"
            lines.append(text)
    return "\n".join(lines) + "\n"
