"""A benchmark's report: its tables, the host it ran on, its result written
as ``<name>.md`` and ``<name>.json``, and its rows of summary.md."""

from __future__ import annotations

import datetime
import json
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

from cloneguard.harness.process import REPO_ROOT
from cloneguard.harness.report.env import git_info, host_info, python_version

from .figures import fmt_ms
from .goals import Goal


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[dict] = field(default_factory=list)

    def __post_init__(self):
        if len(set(self.columns)) != len(self.columns):
            raise ValueError(f"{self.title}: column names must be distinct: {self.columns}")

    def add(self, *cells) -> None:
        if len(cells) != len(self.columns):
            raise ValueError(f"{self.title}: {len(cells)} cells for {len(self.columns)} columns")
        self.rows.append(dict(zip(self.columns, (str(c) for c in cells), strict=True)))

    def markdown(self) -> str:
        def esc(s: str) -> str:
            return s.replace("|", "\\|")

        lines = [
            "| " + " | ".join(esc(c) for c in self.columns) + " |",
            "|" + "|".join("---" for _ in self.columns) + "|",
        ]
        lines += ["| " + " | ".join(esc(r[c]) for c in self.columns) + " |" for r in self.rows]
        return "\n".join(lines)

    def as_json(self) -> dict:
        return {"title": self.title, "columns": self.columns, "rows": self.rows}


def host() -> dict:
    info = host_info()
    info["python"] = python_version()
    info["date"] = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    info["git"] = git_info(REPO_ROOT)
    return info


def host_line(info: dict) -> str:
    git = info.get("git") or {}
    commit = (git.get("commit") or "?")[:10] + (" (with uncommitted changes)" if git.get("dirty") else "")
    return (
        f"kernel {info['kernel']} ({info['machine']}), CPU {info['cpu_model']} "
        f"({info['cpu_count']} CPUs, {info['cpu_usable']} usable), {info['glibc']}, "
        f"{info['python']}, git {commit}, {info['date']}"
    )


@dataclass
class Result:
    name: str
    title: str
    command: str
    params: dict
    tables: list[Table]
    goals: list[Goal]
    notes: list[str]
    summary: list[dict]  # rows for summary.md (see SUMMARY_COLUMNS)
    raw: dict
    cleanup: list[str]  # problems found after clean-up; [] when clean
    host: dict = field(default_factory=host)
    #: more files written beside <name>.md (a picture: name -> text)
    attachments: dict[str, str] = field(default_factory=dict)

    def markdown(self) -> str:
        out = [
            f"# {self.title}",
            "",
            f"Command (from the repository root, venv active): `{self.command}`",
            "",
            f"Host: {host_line(self.host)}",
            "",
        ]
        for table in self.tables:
            out += [f"## {table.title}", "", table.markdown(), ""]
        if self.goals:
            goals = Table("Goals", ["goal", "judged on", "measured", "verdict"])
            for g in self.goals:
                goals.add(*g.row().values())
            out += ["## Goals", "", goals.markdown(), ""]
        if self.notes:
            out += ["## Method and notes", ""] + [f"- {n}" for n in self.notes] + [""]
        out += [
            "Clean-up: "
            + (
                "every container stopped, no process or /dev/shm segment left."
                if not self.cleanup
                else "PROBLEMS: " + "; ".join(self.cleanup)
            ),
            "",
        ]
        return "\n".join(out)

    def as_json(self) -> dict:
        return {
            "name": self.name,
            "title": self.title,
            "command": self.command,
            "invoked_as": shlex.join([Path(sys.executable).name, *sys.argv]),
            "host": self.host,
            "params": self.params,
            "tables": [t.as_json() for t in self.tables],
            "goals": [
                {"goal": g.goal, "judged_on": g.measure, "measured": g.measured, "met": g.met, "verdict": g.verdict}
                for g in self.goals
            ],
            "notes": self.notes,
            "summary": self.summary,
            "cleanup": self.cleanup,
            "raw": self.raw,
        }

    def write(self, out_dir: Path) -> tuple[Path, Path]:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        md, js = out_dir / f"{self.name}.md", out_dir / f"{self.name}.json"
        md.write_text(self.markdown())
        js.write_text(json.dumps(self.as_json(), indent=1) + "\n")
        for name, text in self.attachments.items():
            (out_dir / name).write_text(text)
        return md, js


SUMMARY_COLUMNS = ["benchmark", "measure", "mode", "n", "median", "p90", "goal", "verdict"]


def summary_row(
    benchmark: str,
    measure: str,
    mode: str,
    st: dict | None,
    unit: str = "ms",
    goal: str = "",
    verdict: str = "",
    median: str | None = None,
    p90: str | None = None,
) -> dict:
    st = st or {}
    return {
        "benchmark": benchmark,
        "measure": measure,
        "mode": mode,
        "n": str(st.get("n", "")),
        "median": median if median is not None else (f"{fmt_ms(st.get('median'))} {unit}" if st else ""),
        "p90": p90 if p90 is not None else (f"{fmt_ms(st.get('p90'))} {unit}" if st else ""),
        "goal": goal,
        "verdict": verdict,
    }
