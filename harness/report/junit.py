"""junit.xml of a run's scenarios, for runs where pytest's own writer did
not write it (a merge of shards, a session that named no scenarios)."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

from .model import Scenario, write_atomic


def _classname(nodeid: str) -> tuple[str, str]:
    parts = nodeid.split("::")
    module = parts[0]
    if module.endswith(".py"):
        module = module[:-3]
    module = module.replace("/", ".").replace("\\", ".")
    return ".".join([module] + parts[1:-1]), parts[-1] if len(parts) > 1 else parts[0]


def write_junit(scenarios: list[Scenario], path: Path) -> Path:
    """A JUnit XML of the scenarios, for sessions where pytest's own writer
    was not pointed at the report directory."""
    suite = ET.Element("testsuite", name="cloneguard-scenarios")
    counts = {"failures": 0, "errors": 0, "skipped": 0}
    total_time = 0.0
    for s in scenarios:
        classname, name = _classname(s.nodeid)
        case = ET.SubElement(suite, "testcase", classname=classname, name=name, time=f"{s.duration_s:.3f}")
        total_time += s.duration_s
        if s.outcome == "failed":
            counts["failures"] += 1
            ET.SubElement(case, "failure", message=s.message or "failed").text = s.longrepr or ""
        elif s.outcome in ("error", None):
            counts["errors"] += 1
            ET.SubElement(case, "error", message=s.message or "error").text = s.longrepr or ""
        elif s.outcome == "skipped":
            counts["skipped"] += 1
            ET.SubElement(case, "skipped", message=s.message or "skipped")
    suite.set("tests", str(len(scenarios)))
    for k, v in counts.items():
        suite.set(k, str(v))
    suite.set("time", f"{total_time:.3f}")
    suites = ET.Element("testsuites")
    suites.append(suite)
    ET.indent(suites)
    write_atomic(path, ET.tostring(suites, encoding="unicode", xml_declaration=True) + "\n")
    return path
