"""Join the reports of a run split into shards (``--shard K/N``) into one.

Scenarios are joined by node id: their trials are put together (in plan
order; a trial index met twice means two runs overlap: refused), hangs and
notes kept, and every expectation judged anew on all the trials, as the
unsharded run would have. Rates, intervals and latency statistics are
derived from the trial records when the report is read or rendered, so they
come out of the joined trials by construction.

Runs are joined only when they ran the same plan (seed, deep, forced trial
count) and, unless ``allow_mixed_commits``, the same commit; the merged
report's ``run.shards`` names each part (run id, shard, host, commit,
workers, duration).
"""

from __future__ import annotations

import secrets
from datetime import UTC, datetime
from pathlib import Path

from .junit import write_junit
from .model import JUNIT_XML, REPORT_HTML, Expectation, Report, RunInfo, Scenario
from .render import write_html


class MergeError(ValueError):
    pass


def _commit(report: Report) -> str:
    git = report.run.git or {}
    return f"{git.get('commit') or '?'}{' (dirty)' if git.get('dirty') else ''}"


def _check_parts(reports: list[Report], allow_mixed_commits: bool) -> None:
    if not reports:
        raise MergeError("nothing to merge")
    plans = {repr(sorted((r.run.plan or {}).items())) for r in reports}
    if len(plans) > 1:
        raise MergeError(
            "the runs made different trial plans (--seed/--deep/--trials): "
            + "; ".join(f"{r.run.id}: {r.run.plan}" for r in reports)
        )
    commits = {_commit(r) for r in reports}
    if len(commits) > 1 and not allow_mixed_commits:
        raise MergeError(
            "the runs are of different commits ("
            + ", ".join(f"{r.run.id}: {_commit(r)}" for r in reports)
            + "); merge them anyway with --allow-mixed-commits"
        )
    shards = [r.run.shard for r in reports if r.run.shard]
    if len(set(shards)) != len(shards):
        raise MergeError(f"the same shard is given twice: {sorted(shards)}")
    totals = {s.split("/")[1] for s in shards}
    if len(totals) > 1:
        raise MergeError(f"shards of different splits: {sorted(shards)}")


def _join(nodeid: str, parts: list[Scenario]) -> Scenario:
    ran = [p for p in parts if p.outcome != "skipped"] or parts
    first = ran[0]
    joined = Scenario(
        nodeid=nodeid,
        name=first.name,
        fault=first.fault,
        profile=first.profile,
        mitigations=dict(first.mitigations),
        claim=first.claim,
        started=min((p.started for p in ran if p.started), default=None),
        used_resilience=any(p.used_resilience for p in parts),
        duration_s=round(sum(p.duration_s for p in parts), 3),
    )
    seen: dict[int, str] = {}
    for p in ran:
        for t in p.trials:
            if t.index in seen:
                raise MergeError(f"{nodeid}: trial {t.index} was run twice")
            seen[t.index] = p.nodeid
            joined.trials.append(t)
        joined.hangs.extend(p.hangs)
        joined.notes.extend(n for n in p.notes if n not in joined.notes)
    joined.trials.sort(key=lambda t: t.index)
    joined.hangs.sort(key=lambda h: (h.trial is None, h.trial))
    counts = joined.counts()
    wanted = []
    for p in ran:
        for e in p.expectations:
            key = (e.outcome, e.at_least, e.at_most)
            if key not in wanted:
                wanted.append(key)
    joined.expectations = [
        Expectation.judged(
            outcome, at_least=lo, at_most=hi, successes=counts.get(outcome, 0), trials=len(joined.trials)
        )
        for outcome, lo, hi in wanted
    ]
    # pytest's verdict: a shard judges no expectation (merge does), so a part
    # that failed, failed for another reason, and so does the scenario.
    failures = [p for p in ran if p.outcome in ("failed", "error")]
    if failures:
        joined.outcome, joined.message = failures[0].outcome, failures[0].message
        joined.longrepr = "\n\n".join(p.longrepr for p in failures if p.longrepr) or None
    elif not joined.expectations_met():
        joined.outcome = "failed"
        unmet = [e for e in joined.expectations if e.met is False]
        joined.message = "; ".join(
            f"expected {e.outcome} rate {e.requirement()}, measured {e.successes}/{e.trials}" for e in unmet
        )
    elif all(p.outcome == "skipped" for p in parts):
        joined.outcome, joined.message = "skipped", first.message
    else:
        joined.outcome = "passed"
    return joined


def merge_reports(reports: list[Report], *, allow_mixed_commits: bool = False) -> Report:
    _check_parts(reports, allow_mixed_commits)
    order: list[str] = []
    parts: dict[str, list[Scenario]] = {}
    for r in reports:
        for s in r.scenarios:
            if s.nodeid not in parts:
                order.append(s.nodeid)
                parts[s.nodeid] = []
            parts[s.nodeid].append(s)
    runs = [r.run for r in reports]
    started = min((r.started for r in runs if r.started), default=None)
    finished = max((r.finished for r in runs if r.finished), default=None)
    now = datetime.now(UTC)
    run = RunInfo(
        id=now.strftime("%Y%m%dT%H%M%SZ") + "-merged-" + secrets.token_hex(2),
        label=f"merge of {len(reports)} run(s)",
        started=started,
        finished=finished,
        duration_s=round(sum(r.duration_s or 0.0 for r in runs), 3),
        exit_status=0 if all(r.exit_status in (0, None) for r in runs) else 1,
        pytest_args=list(runs[0].pytest_args),
        python=runs[0].python,
        host=dict(runs[0].host),
        git=dict(runs[0].git),
        container_exe=runs[0].container_exe,
        deep=any(r.deep for r in runs),
        workers=sum(r.workers for r in runs),
        plan=dict(runs[0].plan),
        shards=[
            {
                "id": r.id,
                "shard": r.shard,
                "host": (r.host or {}).get("hostname"),
                "commit": (r.git or {}).get("commit"),
                "dirty": (r.git or {}).get("dirty"),
                "workers": r.workers,
                "duration_s": r.duration_s,
                "started": r.started,
            }
            for r in runs
        ],
    )
    return Report(run=run, scenarios=[_join(n, parts[n]) for n in order])


def write_merged(report: Report, out: Path) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report.run.junit, report.run.junit_writer = JUNIT_XML, "cloneguard (merge)"
    write_junit(report.scenarios, out / JUNIT_XML)
    report.save_json(out)
    write_html(report, out / REPORT_HTML)
    return out
