"""Join the reports of one suite's runs into one: the shards of a run
(``--shard K/N``), and runs of other seeds (a CI matrix of ``--seed``s).

Scenarios are joined by node id: their trials are put together, hangs and
notes kept, and every expectation judged anew on all the trials, as one run
of them all would have. Rates, intervals and latency statistics are derived
from the trial records when the report is read or rendered, so they come
out of the joined trials by construction.

A trial is known by its run's base seed and its index in that run's plan
(its own seed follows from the two): met twice, two runs overlap, and the
merge is refused. Runs of one base seed must have made the same plan
(deep, forced trial count) and be distinct shards of it. Runs of several
base seeds are independent trials of the same claims: their trials are
numbered anew, base seed by base seed (each keeps its own seed, which
``reproduce`` replays, and says which run and index it was), and the
merged plan lists the seeds. Unless ``allow_mixed_commits``, every run
must be of the same commit; the merged report's ``run.shards`` names each
part (run id, seed, shard, host, commit, workers, duration).
"""

from __future__ import annotations

import secrets
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from .junit import write_junit
from .model import JUNIT_XML, REPORT_HTML, Expectation, Hang, Report, RunInfo, Scenario, Trial
from .render import write_html


class MergeError(ValueError):
    pass


def _commit(report: Report) -> str:
    git = report.run.git or {}
    return f"{git.get('commit') or '?'}{' (dirty)' if git.get('dirty') else ''}"


def _seed_of(report: Report) -> object:
    return (report.run.plan or {}).get("seed")


def _by_seed(reports: list[Report]) -> dict:
    """The runs grouped by base seed, in the order first given."""
    groups: dict = {}
    for r in reports:
        groups.setdefault(repr(_seed_of(r)), []).append(r)
    return groups


def _check_parts(reports: list[Report], allow_mixed_commits: bool) -> None:
    if not reports:
        raise MergeError("nothing to merge")
    for group in _by_seed(reports).values():
        _check_one_plan(group)
    if len(reports) > 1 and any(isinstance(_seed_of(r), list) for r in reports):
        raise MergeError("a merge of several seeds is not merged again: merge all its parts at once")
    commits = {_commit(r) for r in reports}
    if len(commits) > 1 and not allow_mixed_commits:
        raise MergeError(
            "the runs are of different commits ("
            + ", ".join(f"{r.run.id}: {_commit(r)}" for r in reports)
            + "); merge them anyway with --allow-mixed-commits"
        )


def _check_one_plan(reports: list[Report]) -> None:
    """Runs of one base seed: one plan, distinct shards of one split."""
    plans = {repr(sorted((r.run.plan or {}).items())) for r in reports}
    if len(plans) > 1:
        raise MergeError(
            "runs of the same --seed made different trial plans (--deep/--trials): "
            + "; ".join(f"{r.run.id}: {r.run.plan}" for r in reports)
        )
    shards = [r.run.shard for r in reports if r.run.shard]
    if len(set(shards)) != len(shards):
        raise MergeError(f"the same shard is given twice: {sorted(shards)}")
    totals = {s.split("/")[1] for s in shards}
    if len(totals) > 1:
        raise MergeError(f"shards of different splits: {sorted(shards)}")


def _join(nodeid: str, seeded_parts: list[tuple[Any, Scenario]]) -> Scenario:
    """One scenario from its parts, each with its run's base seed."""
    parts = [p for _, p in seeded_parts]
    ran = [sp for sp in seeded_parts if sp[1].outcome != "skipped"] or seeded_parts
    first = ran[0][1]
    joined = Scenario(
        nodeid=nodeid,
        name=first.name,
        fault=first.fault,
        profile=first.profile,
        mitigations=dict(first.mitigations),
        units={k: v for p in parts for k, v in p.units.items()},
        claim=first.claim,
        started=min((p.started for _, p in ran if p.started), default=None),
        used_resilience=any(p.used_resilience for p in parts),
        duration_s=round(sum(p.duration_s for p in parts), 3),
    )
    seeds = list(dict.fromkeys(repr(seed) for seed, _ in seeded_parts))
    keyed: dict[tuple[int, int], Trial] = {}  # (base seed's place, index) -> trial
    hangs: list[tuple[int, Hang]] = []
    for seed, p in ran:
        place = seeds.index(repr(seed))
        for t in p.trials:
            if (place, t.index) in keyed:
                raise MergeError(f"{nodeid}: trial {t.index} of --seed {seed} was run twice")
            keyed[(place, t.index)] = t
        hangs.extend((place, h) for h in p.hangs)
        joined.notes.extend(n for n in p.notes if n not in joined.notes)
    order = sorted(keyed)
    if len(seeds) == 1:  # one plan: its indices stand
        joined.trials = [keyed[k] for k in order]
        joined.hangs = [h for _, h in hangs]
    else:  # numbered anew, base seed by base seed
        new = {k: i for i, k in enumerate(order)}
        for place, index in order:
            t = keyed[(place, index)]
            run = f"--seed {seeds[place]}, trial {index}"
            joined.trials.append(replace(t, index=new[(place, index)], details={**t.details, "run": run}))
        joined.hangs = [replace(h, trial=None if h.trial is None else new[(place, h.trial)]) for place, h in hangs]
    joined.hangs.sort(key=lambda h: (h.trial is None, h.trial))
    counts = joined.counts()
    wanted = []
    for _, p in ran:
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
    failures = [p for _, p in ran if p.outcome in ("failed", "error")]
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
    parts: dict[str, list[tuple[Any, Scenario]]] = {}
    for r in reports:
        for s in r.scenarios:
            if s.nodeid not in parts:
                order.append(s.nodeid)
                parts[s.nodeid] = []
            parts[s.nodeid].append((_seed_of(r), s))
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
        project=runs[0].project,
        packages=dict(runs[0].packages),
        container_exe=runs[0].container_exe,
        deep=any(r.deep for r in runs),
        workers=sum(r.workers for r in runs),
        plan=_merged_plan(reports),
        shards=[
            {
                "id": r.id,
                "seed": (r.plan or {}).get("seed"),
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


def _merged_plan(reports: list[Report]) -> dict:
    """The plan of one seed's runs; of several, their seeds listed (and
    deep/trials where all agree, else each run's)."""
    groups = _by_seed(reports)
    if len(groups) == 1:
        return dict(reports[0].run.plan)
    firsts = [g[0].run.plan or {} for g in groups.values()]
    plan: dict[str, Any] = {"seed": [p.get("seed") for p in firsts]}
    for key in ("deep", "trials"):
        values = [p.get(key) for p in firsts]
        plan[key] = values[0] if all(v == values[0] for v in values) else values
    return plan


def write_merged(report: Report, out: Path) -> Path:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    report.run.junit, report.run.junit_writer = JUNIT_XML, "cloneguard (merge)"
    write_junit(report.scenarios, out / JUNIT_XML)
    report.save_json(out)
    write_html(report, out / REPORT_HTML)
    return out
