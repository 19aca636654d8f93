"""Compare two runs: survival rates and median latencies, scenario by scenario.

Scenarios are matched by pytest node id; those left over are matched by
(fault, profile, mitigations), then by (fault, profile), when that pairs
exactly one scenario of each run.

Whether a change in survival rate is significant is decided by one of two
methods (the output says which):

``z``        two-proportion z-test, pooled, two-sided, at ``alpha`` (default)
``wilson``   the two 95% Wilson score intervals do not overlap (stricter)
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from . import stats
from .charts import fmt_ms
from .model import Report, Scenario

METHODS = {
    "z": "two-proportion z-test (pooled, two-sided)",
    "wilson": "non-overlapping 95% Wilson score intervals",
}


@dataclass
class LatencyDelta:
    series: str
    median_a: float | None
    median_b: float | None
    unit: str = "ms"

    @property
    def ratio(self) -> float | None:
        if self.median_a is None or self.median_b is None or self.median_a == 0:
            return None
        return self.median_b / self.median_a


@dataclass
class ScenarioDelta:
    a: Scenario
    b: Scenario
    matched_by: str
    survival_a: stats.Proportion
    survival_b: stats.Proportion
    p_value: float | None
    significant: bool
    latency: list[LatencyDelta] = field(default_factory=list)

    @property
    def change(self) -> float | None:
        if self.survival_a.rate is None or self.survival_b.rate is None:
            return None
        return self.survival_b.rate - self.survival_a.rate

    @property
    def verdict(self) -> str:
        """worse / better (significant changes only), same, or n/a."""
        change = self.change
        if change is None:
            return "n/a"
        if self.significant and change < 0:
            return "worse"
        if self.significant and change > 0:
            return "better"
        return "same"


@dataclass
class Comparison:
    a: Report
    b: Report
    method: str
    alpha: float
    deltas: list[ScenarioDelta]
    only_a: list[Scenario]
    only_b: list[Scenario]

    @property
    def regressions(self) -> list[ScenarioDelta]:
        return [d for d in self.deltas if d.verdict == "worse"]

    @property
    def improvements(self) -> list[ScenarioDelta]:
        return [d for d in self.deltas if d.verdict == "better"]


def _key_full(s: Scenario) -> tuple[str, str, str] | None:
    if s.fault is None or s.profile is None:
        return None
    return (s.fault, s.profile, json.dumps(s.mitigations, sort_keys=True, default=str))


def _key_short(s: Scenario) -> tuple[str, str] | None:
    if s.fault is None or s.profile is None:
        return None
    return (s.fault, s.profile)


def match_scenarios(
    a: Report, b: Report
) -> tuple[list[tuple[Scenario, Scenario, str]], list[Scenario], list[Scenario]]:
    """Pairs (scenario of A, scenario of B, how matched), then the unmatched of A and of B."""
    pairs = []
    b_by_id = {s.nodeid: s for s in b.scenarios}
    rest_a = []
    used_b = set()
    for s in a.scenarios:
        other = b_by_id.get(s.nodeid)
        if other is not None and id(other) not in used_b:
            pairs.append((s, other, "nodeid"))
            used_b.add(id(other))
        else:
            rest_a.append(s)
    rest_b = [s for s in b.scenarios if id(s) not in used_b]

    for key, label in ((_key_full, "fault+profile+mitigations"), (_key_short, "fault+profile")):
        groups_a: dict = {}
        groups_b: dict = {}
        for s in rest_a:
            groups_a.setdefault(key(s), []).append(s)
        for s in rest_b:
            groups_b.setdefault(key(s), []).append(s)
        matched: set = set()
        for k, members in groups_a.items():
            if k is None or len(members) != 1 or len(groups_b.get(k, ())) != 1:
                continue
            sa, sb = members[0], groups_b[k][0]
            pairs.append((sa, sb, label))
            matched.update((id(sa), id(sb)))
        rest_a = [s for s in rest_a if id(s) not in matched]
        rest_b = [s for s in rest_b if id(s) not in matched]
    order = {id(s): i for i, s in enumerate(a.scenarios)}
    pairs.sort(key=lambda p: order[id(p[0])])
    return pairs, rest_a, rest_b


def significance(
    pa: stats.Proportion, pb: stats.Proportion, method: str = "z", alpha: float = 0.05
) -> tuple[bool, float | None]:
    """(significant, p-value or None) for the change from ``pa`` to ``pb``."""
    if not pa.trials or not pb.trials:
        return False, None
    if method == "z":
        _, p = stats.two_proportion_z_test(pa.successes, pa.trials, pb.successes, pb.trials)
        return p < alpha, p
    if method == "wilson":
        return not stats.intervals_overlap(pa, pb), None
    raise ValueError(f"unknown method {method!r}; one of {sorted(METHODS)}")


def compare_reports(a: Report, b: Report, method: str = "z", alpha: float = 0.05) -> Comparison:
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; one of {sorted(METHODS)}")
    pairs, only_a, only_b = match_scenarios(a, b)
    deltas = []
    for sa, sb, how in pairs:
        pa, pb = sa.survival(), sb.survival()
        significant, p_value = significance(pa, pb, method, alpha)
        lat_a, lat_b = sa.latency_summaries(), sb.latency_summaries()
        latency = [
            LatencyDelta(
                name,
                lat_a[name].median if name in lat_a else None,
                lat_b[name].median if name in lat_b else None,
                sa.unit(name) if name in lat_a else sb.unit(name),
            )
            for name in list(lat_a) + [n for n in lat_b if n not in lat_a]
        ]
        deltas.append(ScenarioDelta(sa, sb, how, pa, pb, p_value, significant, latency))
    return Comparison(a, b, method, alpha, deltas, only_a, only_b)


def _prop(p: stats.Proportion) -> str:
    if not p.trials or p.rate is None:
        return "no trials"
    return f"{p.successes}/{p.trials} {p.rate * 100:5.1f}% [{p.low * 100:.1f}–{p.high * 100:.1f}]"


def _run_line(tag: str, r: Report) -> str:
    run = r.run
    bits = [run.id]
    if run.label:
        bits.append(f"({run.label})")
    if run.started:
        bits.append(run.started)
    commit = (run.git or {}).get("commit")
    if commit:
        bits.append(f"commit {commit[:12]}" + ("+dirty" if run.git.get("dirty") else ""))
    where = f"  [{r.directory}]" if r.directory else ""
    return f"{tag}: {' '.join(bits)}{where}"


def format_comparison(c: Comparison) -> str:
    lines = [_run_line("A", c.a), _run_line("B", c.b)]
    alpha = f", alpha {c.alpha:g}" if c.method == "z" else ""
    lines.append(f"significance: {METHODS[c.method]}{alpha}")
    lines.append("")
    for i, d in enumerate(c.deltas):
        if i:
            lines.append("")
        title = d.a.nodeid
        tags = "/".join(x for x in (d.a.fault, d.a.profile) if x)
        if tags:
            title += f"  [{tags}]"
        if d.matched_by != "nodeid":
            title += f"  (matched by {d.matched_by}: B is {d.b.nodeid})"
        lines.append(title)
        change = d.change
        change_text = "" if change is None else f"  {change * 100:+.1f} pp"
        p_text = f"  p={d.p_value:.3g}" if d.p_value is not None else ""
        verdict = {
            "worse": "WORSE (significant)",
            "better": "better (significant)",
            "same": "no significant change",
            "n/a": "n/a",
        }[d.verdict]
        lines.append(f"  survived  {_prop(d.survival_a)}  ->  {_prop(d.survival_b)}{change_text}{p_text}  {verdict}")
        for lat in d.latency:
            ratio = f"  x{lat.ratio:.2f}" if lat.ratio is not None else ""
            ma = f"{fmt_ms(lat.median_a)} {lat.unit}" if lat.median_a is not None else "–"
            mb = f"{fmt_ms(lat.median_b)} {lat.unit}" if lat.median_b is not None else "–"
            what = "latency" if lat.unit == "ms" else "measured"
            lines.append(f"  {what} {lat.series}: median {ma} -> {mb}{ratio}")
    if c.only_a:
        lines.append("")
        lines.append("only in A:")
        lines.extend(f"  {s.nodeid}  {_prop(s.survival())}" for s in c.only_a)
    if c.only_b:
        lines.append("")
        lines.append("only in B:")
        lines.extend(f"  {s.nodeid}  {_prop(s.survival())}" for s in c.only_b)
    lines.append("")
    lines.append(
        f"{len(c.deltas)} matched, {len(c.regressions)} significantly worse, "
        f"{len(c.improvements)} significantly better, {len(c.only_a)} only in A, "
        f"{len(c.only_b)} only in B"
    )
    return "\n".join(lines)
